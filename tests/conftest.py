"""Shared test helpers: where the real meshes are, and the first-hit agreement rule."""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np
import pytest

#: ../shared/meshes beside the checkout (present in CI, absent in a user's fresh clone).
SHARED_MESHES = Path(__file__).resolve().parents[2] / "shared" / "meshes"


def shared_mesh(name: str) -> Path:
    """Path of a real mesh, or skip the test with the reason."""
    path = SHARED_MESHES / name
    if not path.exists():
        pytest.skip(f"real meshes not available: {path} is absent (../shared is beside the checkout in CI only)")
    return path


def traverse_isas() -> list[str]:
    """The sign stages the timed twin can run on this host ('sse2', and 'avx2' where the CPU has it)."""
    from calibrate import _kernels

    found = []
    try:
        for isa in ("sse2", "avx2"):
            try:
                _kernels.set_traverse_isa(isa)
                found.append(isa)
            except ValueError:
                pass
    finally:
        _kernels.set_traverse_isa("auto")
    return found


@contextlib.contextmanager
def traverse_isa(isa: str):
    """Run the timed twin with the given sign stage inside the block; the host's best after."""
    from calibrate import _kernels

    _kernels.set_traverse_isa(isa)
    try:
        yield
    finally:
        _kernels.set_traverse_isa("auto")


def first_hit_disagreements(t, prim, t_ref, prim_ref, rel_tol: float = 1e-9):
    """Rays whose first hit differs from the reference, and the number of ties.

    A ray agrees when both miss, or both hit at t within ``rel_tol`` and on the
    same triangle; a tie is a ray whose t agrees but whose triangle differs
    (two triangles met at the same point: a shared edge or a duplicate).
    Returns (indices of disagreeing rays, tie count).
    """
    t = np.asarray(t)
    t_ref = np.asarray(t_ref)
    both_miss = np.isinf(t) & np.isinf(t_ref) & (prim < 0) & (prim_ref < 0)
    finite = np.isfinite(t) & np.isfinite(t_ref)
    close = np.zeros_like(finite)
    close[finite] = np.abs(t[finite] - t_ref[finite]) <= rel_tol * np.abs(t_ref[finite])
    same = both_miss | (close & (prim == prim_ref))
    ties = close & (prim != prim_ref)
    return np.flatnonzero(~(same | ties)), int(ties.sum())


def planted_counts(rng: np.random.Generator, j: int, rays: int) -> dict:
    """Batch-total counts of synthetic in-context configuration ``j`` for the fit's planted-constant
    tests: 1-60 steps and 3-100 tests per ray (log-uniform), subgrids (1-13 per ray) in every fourth."""
    steps_pr = np.exp(rng.uniform(np.log(1.0), np.log(60.0)))
    tests_pr = np.exp(rng.uniform(np.log(3.0), np.log(100.0)))
    sub_pr = rng.uniform(1.0, 13.0) if j % 4 == 0 else 0.0
    return dict(steps=int(rays * steps_pr), tests=int(rays * tests_pr), subgrids=int(rays * sub_pr))


def assert_planted_recovered(result, truth: dict, names, rel: float = 0.05) -> None:
    """Each named constant of a fit: median within ``rel`` of the planted truth, the truth inside
    its 95% interval."""
    for name in names:
        c = result.constants[name]
        assert c["median"] == pytest.approx(truth[name], rel=rel), name
        assert c["ci95"][0] <= truth[name] <= c["ci95"][1], name


def planted_calibration(recs: list[dict], priors: dict):
    """The in-context fit of synthetic records (every optional count they carry, each kept when
    the timings call for it) and a calibration made from it: (FitResult, calibration dict)."""
    from calibrate import calfile

    design = calfile.design_from_measurements(recs, "in_context", optional=calfile.OPTIONAL_COUNT_FIELDS)
    result = calfile.fit_in_context(design, seed=0, priors=priors)
    cal = calfile.from_fit(result, fingerprint={"cpu_model": "Test CPU"}, measurements=recs, meta={})
    return result, cal


def exported_header(cal: dict, tmp_path: Path, condition: str) -> str:
    """Export ``cal``'s header into ``tmp_path``, check that a C99 program including it
    (-Wall -Wextra -Werror -pedantic) finds ``condition`` true, and return the header's text."""
    import subprocess

    from calibrate import calfile
    from calibrate.export import export

    path = tmp_path / "cal.json"
    calfile.save(path, cal)
    header = tmp_path / "grid_tuning.h"
    export(header, calibration=path, rays=None)
    prog = tmp_path / "use.c"
    prog.write_text(f'#include "grid_tuning.h"\nint main(void) {{ return ({condition}) ? 0 : 1; }}\n')
    subprocess.run(["cc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", f"-I{tmp_path}", str(prog),
                    "-o", str(tmp_path / "use"), "-lm"], check=True)
    assert subprocess.run([str(tmp_path / "use")]).returncode == 0
    return header.read_text()


@pytest.fixture
def one_capacity(monkeypatch):
    """The memory model with one cache size instead of the spread around it
    (models.memory.CACHE_SPREAD_OCTAVES = 0): the single-capacity laws under test."""
    import models.memory

    monkeypatch.setattr(models.memory, "CACHE_SPREAD_OCTAVES", 0.0)
