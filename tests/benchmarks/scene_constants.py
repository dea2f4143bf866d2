"""Benchmark: what one scene's timings say a step and a test cost, beside the calibration's constants.

    python tests/benchmarks/scene_constants.py [--calibration FILE (default calibration.json)]
        [--rays camera|isotropic ...] [--out results.json]

A calibration fits one T_step and one T_int to the in-context timings of every
built-in scene.  This script reads a calibration's stored measurements and, for
each ray set and scene, fits that scene's uniform grids alone (coarse to fine, the
same rays) by relative least squares:

    time per ray = a + T_step * steps per ray + T_int * tests per ray

(``a`` takes in what is the same at every resolution of one scene: the set-up,
the hits, the occupied cells entered, which vary little along one scene's series).
Printed per scene: the local T_step, T_int and r, their relative RMS misfit, and
the calibration's own residuals (measured / predicted by the ray set's fitted
constants - 1) from the coarsest grid to the finest; and, where the records carry
them (calibrations made since 2026-12-05), the walks' occupancy changes per ray
(:meth:`calibrate.Grid.count`), which rise with the resolution where a scene's
residuals do.

When the local fits are close (a few per cent) and their T_step differ between
scenes, one T_step cannot describe them all: the residuals of the calibration then
run from negative to positive along a scene's series, which moves where its
optimum lies.  Nothing is timed: the figures are the stored measurements'
(docs/calibration.md, "One T_step for every scene").
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from calibrate import calfile
from calibrate import fit as F
from calibrate._io import UserError, atomic_write_text

#: Fewest uniform grids of one scene for a local fit (three unknowns, and a misfit to report).
MIN_GRIDS = 5


def local_fit(steps, tests, time) -> dict:
    """Relative least squares of time = a + T_step * steps + T_int * tests (per-ray arrays).

    Returns {a, t_step_ns, t_int_ns, ratio, rms}: ``rms`` the relative RMS misfit."""
    steps, tests, time = (np.asarray(x, dtype=np.float64) for x in (steps, tests, time))
    if steps.shape[0] < MIN_GRIDS:
        raise ValueError(f"a local fit needs at least {MIN_GRIDS} grids, got {steps.shape[0]}")
    design = np.column_stack([np.ones_like(time), steps, tests]) / time[:, None]
    coef, *_ = np.linalg.lstsq(design, np.ones_like(time), rcond=None)
    rel = design @ coef - 1.0
    a, t_step, t_int = (float(c) for c in coef)
    return dict(a=a, t_step_ns=t_step, t_int_ns=t_int, ratio=t_int / t_step if t_step != 0 else float("nan"),
                rms=float(np.sqrt(np.mean(rel ** 2))))


def predicted_ns(constants: dict, record: dict) -> float:
    """A record's batch time by the medians of ``constants`` (name -> {median, ...})."""
    return sum(constants[name]["median"] * float(record.get(count, 0) or 0)
               for name, count in zip(F.CONSTANT_NAMES, F.COUNT_KEYS) if constants.get(name))


def _uniform(record) -> bool:
    return not str(record["resolution"]).startswith("L")


def scene_rows(cal: dict, ray_set: str) -> list[dict]:
    """One row per scene of ``ray_set``: the local fit and the calibration's residuals, coarse to fine."""
    constants = calfile.fit_for_rays(cal, ray_set)[0]["constants"]
    recs = [r for r in calfile.apply_drift(cal["measurements"])
            if r["kind"] == "in_context" and r.get("ray_set") == ray_set and r["values_ns"] and _uniform(r)]
    out = []
    for scene in sorted({r["scene"] for r in recs}):
        mine = sorted((r for r in recs if r["scene"] == scene), key=lambda r: r["steps"] / r["rays"])
        rays = np.array([r["rays"] for r in mine], dtype=np.float64)
        time = np.array([np.median(r["values_ns"]) for r in mine]) / rays
        steps = np.array([r["steps"] for r in mine]) / rays
        tests = np.array([r["tests"] for r in mine]) / rays
        row = dict(scene=scene, grids=len(mine), resolutions=[r["resolution"] for r in mine],
                   steps_per_ray=steps.tolist(), tests_per_ray=tests.tolist(), ns_per_ray=time.tolist(),
                   residuals=[float(np.median(r["values_ns"]) / predicted_ns(constants, r) - 1.0) for r in mine])
        if all("changes" in r for r in mine):
            row["changes_per_ray"] = (np.array([r["changes"] for r in mine]) / rays).tolist()
        if len(mine) >= MIN_GRIDS:
            row["local"] = local_fit(steps, tests, time)
        out.append(row)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--calibration", default="calibration.json")
    ap.add_argument("--rays", nargs="+", default=None, help="ray sets (default: every one the file fitted)")
    ap.add_argument("--out", default=None, help="write the rows as JSON")
    args = ap.parse_args(argv)
    try:
        cal = calfile.load(args.calibration)
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    sets = args.rays or sorted((cal.get("by_rays") or {}).keys()) or ["isotropic"]
    result = {}
    for ray_set in sets:
        entry, fitted_on = calfile.fit_for_rays(cal, ray_set)
        consts = entry["constants"]
        print(f"{ray_set} rays: the calibration's T_step {consts['t_step_ns']['median']:.2f} ns, "
              f"T_int {consts['t_int_ns']['median']:.3f} ns, r {consts['ratio']['median']:.3f}"
              + ("" if fitted_on else " (pooled: the ray set was not fitted alone)"))
        rows = scene_rows(cal, ray_set)
        print(f"  {'scene':20s} {'grids':>5s} {'T_step':>7s} {'T_int':>7s} {'r':>6s} {'misfit':>7s}   "
              "calibration's residuals, coarse to fine")
        for row in rows:
            loc = row.get("local")
            head = (f"{loc['t_step_ns']:7.2f} {loc['t_int_ns']:7.3f} {loc['ratio']:6.3f} {100 * loc['rms']:6.1f}%"
                    if loc else f"{'-':>7s} {'-':>7s} {'-':>6s} {'-':>7s}")
            res = " ".join(f"{100 * x:+.0f}" for x in row["residuals"])
            print(f"  {row['scene']:20s} {row['grids']:5d} {head}   {res} %")
            if "changes_per_ray" in row:
                ch = " ".join(f"{x:.2f}" for x in row["changes_per_ray"])
                print(f"  {'':20s} {'':5s} {'':7s} {'':7s} {'':6s} {'':7s}   occupancy changes a ray: {ch}")
        result[ray_set] = rows
    if args.out:
        atomic_write_text(Path(args.out), json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
