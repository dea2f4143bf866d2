"""The kernels' own C tests, built without Python: optimised, and under ASan + UBSan."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

KERNELS = Path(__file__).resolve().parents[1] / "kernels"


def _run_make(target: str, build_dir: Path) -> subprocess.CompletedProcess:
    if shutil.which("make") is None or shutil.which("cc") is None:
        pytest.skip("make and a C compiler are needed to build the kernels on their own")
    return subprocess.run(["make", "-C", str(KERNELS), target, f"BUILD={build_dir}"],
                          capture_output=True, text=True, timeout=900)


@pytest.mark.parametrize("target", ["test", "test-sanitize"])
def test_c_kernel_suite(target, tmp_path):
    proc = _run_make(target, tmp_path)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, f"make {target} failed:\n{out[-4000:]}"
    assert " 0 failed" in out and "passed" in out, out[-2000:]
    assert "runtime error" not in out and "ERROR: AddressSanitizer" not in out, out[-4000:]
