"""Fuzz mesh ingestion and grid building for a bounded time (tests/fuzz/fuzz_mesh.py, atheris).

The target runs in a subprocess under libFuzzer for FUZZ_SECONDS, starting from
the seed corpus in tests/fuzz/corpus (new inputs go to a scratch directory, so
the checkout is never changed).  It passes when libFuzzer finishes without a
finding: every bad input was answered by a one-line ValueError, and no grid hit
came before brute force's.  A finding fails the test with the input that caused
it and the target's traceback.
"""

from __future__ import annotations

import importlib.util
import os
import resource
import subprocess
import sys
from pathlib import Path

import pytest

FUZZ_DIR = Path(__file__).resolve().parent / "fuzz"
REPO = FUZZ_DIR.parents[1]
#: Wall-clock seconds of fuzzing (libFuzzer's -max_total_time).
FUZZ_SECONDS = 15
#: Fixed libFuzzer seed: the same mutations every run on the same corpus.
FUZZ_SEED = 1
#: Largest generated input, bytes.
MAX_INPUT_BYTES = 4096
#: Memory the target may use, MB, on top of what it inherits: on Linux a child's peak RSS
#: (what libFuzzer's -rss_limit_mb checks) starts at its parent's, kept across fork and
#: exec, so a pytest worker that has grown to 2.5 GB would fail libFuzzer's default
#: 2,048 MB at its first input.
RSS_BUDGET_MB = 2048

pytestmark = pytest.mark.skipif(importlib.util.find_spec("atheris") is None,
                                reason="atheris is not installed (pip install -e '.[test]' installs it); "
                                       "the fuzz target needs it")


def test_fuzz_mesh_ingestion_and_grid_building(tmp_path):
    found = tmp_path / "new_inputs"
    found.mkdir()
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO)] + [p for p in [os.environ.get("PYTHONPATH")] if p]))
    inherited_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024  # KB on Linux
    cmd = [sys.executable, str(FUZZ_DIR / "fuzz_mesh.py"), str(found), str(FUZZ_DIR / "corpus"),
           f"-rss_limit_mb={inherited_mb + RSS_BUDGET_MB}", f"-malloc_limit_mb={RSS_BUDGET_MB}",
           f"-dict={FUZZ_DIR / 'mesh.dict'}", f"-max_total_time={FUZZ_SECONDS}", f"-seed={FUZZ_SEED}",
           f"-max_len={MAX_INPUT_BYTES}", f"-artifact_prefix={tmp_path}{os.sep}", "-print_final_stats=1"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=FUZZ_SECONDS + 120, cwd=tmp_path)
    log = proc.stdout + proc.stderr
    crashes = sorted(p for p in tmp_path.iterdir() if p.is_file() and p.name.startswith(("crash-", "leak-", "timeout-",
                                                                                          "oom-")))
    assert proc.returncode == 0 and not crashes, (
        f"fuzzing found a problem (exit {proc.returncode}); inputs: "
        f"{[(p.name, p.read_bytes()[:200]) for p in crashes]}\n{log[-4000:]}")
    runs = [line for line in log.splitlines() if line.startswith("stat::number_of_executed_units:")]
    assert runs and int(runs[0].split(":")[-1]) > 0, f"the target ran no input:\n{log[-2000:]}"
