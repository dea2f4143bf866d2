"""Benchmark: the analytic model's counts per ray against the kernel's, scene by scene.

    python tests/benchmarks/count_accuracy.py [--ratio R | --calibration FILE (default calibration.json)]
        [--rays N] [--scales 0.5 1 2] [--meshes DIR] [--only NAME ...] [--out results.json]

For each built-in scene and each mesh in ../shared/meshes (when present): the
single-level resolution ``calibrate predict --fidelity analytic --levels 1`` plans,
scaled per axis by each of ``--scales``; at each, the model's steps, triangle tests
and occupied cells entered per ray (rays stop at their first hit, as the kernel's do;
the terms :func:`models.effects.select_effects` keeps) beside the instrumented
kernel's on ``--rays`` isotropic rays (seeded).  Counting only: nothing is timed, so
the figures are the same on every run and every host.

Also printed, per grid, the changes of occupancy per ray (the model's,
:func:`models.general.occupancy_changes` from the termination sample's grids, and the
kernel's; the median and worst absolute difference at the end), and two figures behind
the test count:

- ``tests/visit``: the kernel's tests per occupied cell entered, beside ``R/occ``,
  the model's references per occupied cell (:func:`models.general.expected_refs` over
  :func:`models.general.occupied_cells`).  Without termination the two are equal
  (Crofton: every cell is entered with the same probability); the figures show how
  near they stay when rays stop.
- ``by distance``: the tests counted as if a ray's tests were spread evenly along the
  distance it covers (the no-termination count scaled by
  :func:`models.general.cell_fraction`), against the kernel's; the model's ``tests``
  are the smaller of that and the count in the occupied cells a ray enters
  (:func:`models.general.stopped_tests_per_ray`).

Not a test: it says where the counts are off and by how much (docs/compare.md,
"What the kernel counts against the model").
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from calibrate import Scene
from calibrate import predict as P
from calibrate._grid import Grid
from calibrate.rays import isotropic
from compare_all import MESHES, scene_names  # this folder: the scripts run as files
from models.effects import select_effects
from models.general import occupancy_changes, occupied_cells, predict_uniform, visits_per_ray

RAY_SEED = 1


def _rel(model: float, kernel: float) -> float | None:
    return None if kernel <= 0 else model / kernel - 1.0


def _pct(x) -> str:
    return "     -" if x is None else f"{100 * x:+5.0f}%"


def measure_scene(scene: Scene, source: dict, scales, n_rays: int) -> list[dict]:
    """One row per scale: the model's counts and the kernel's at the scaled L1 plan.

    source : ``constants``/``samples`` or ``ratio``, as :func:`calibrate.predict.predict` takes them."""
    k = P.resolve_constants(**source)
    stats = P.scene_statistics(scene)
    sel = select_effects(stats, k.t_setup, k.t_step, k.t_int, mailbox=False, termination=True, overlap="exact",
                         levels=1)
    planned = P.predict(scene, fidelity="analytic", levels="1", **source)
    centre = tuple(planned["levels"][0]["resolution"])
    o, d = isotropic(scene.box_lo, scene.box_hi, n_rays, RAY_SEED)
    fsep = stats.separate_fraction
    rows = []
    for s in scales:
        res = P._scaled(centre, s)
        steps, tests, refs, _, _, _ = P._uniform_counts(stats, res, k, sel.terms)
        visits, changes = visits_per_ray(stats, res, terms=sel.terms), occupancy_changes(stats, res)
        occ = occupied_cells(stats, res)
        ks, kt, _, kv, kc = Grid.uniform(scene, res, "watertight").count(o, d, visits=True, changes=True)
        ks, kt, kv, kc = float(ks.mean()), float(kt.mean()), float(kv.mean()), float(kc.mean())
        per_occ = refs / occ if occ > 0 else float("nan")
        _, _, by_distance = predict_uniform(stats, res, 0.0, 1.0, 1.0, overlap="exact", terms=sel.terms)
        rows.append(dict(scene=scene.name, scale=s, resolution=list(res), separate_fraction=fsep,
                         model=dict(steps=steps, tests=tests, visits=visits, changes=changes,
                                    refs_per_occupied=per_occ, tests_by_distance=by_distance),
                         kernel=dict(steps=ks, tests=kt, visits=kv, changes=kc,
                                     tests_per_visit=kt / kv if kv > 0 else None),
                         error=dict(steps=_rel(steps, ks), tests=_rel(tests, kt), visits=_rel(visits, kv),
                                    changes=changes - kc, tests_by_distance=_rel(by_distance, kt))))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    src = ap.add_mutually_exclusive_group()
    src.add_argument("--ratio", type=float, default=None)
    src.add_argument("--calibration", default=None)
    ap.add_argument("--ray-set", default="isotropic", choices=("isotropic", "camera"),
                    help="whose fit of the calibration plans the grids (the rays counted are isotropic)")
    ap.add_argument("--meshes", default=str(MESHES), help="directory of real meshes (default ../shared/meshes)")
    ap.add_argument("--rays", type=int, default=4096, help="isotropic rays counted per grid")
    ap.add_argument("--scales", type=float, nargs="+", default=[0.5, 1.0, 2.0],
                    help="per-axis factors of the planned resolution")
    ap.add_argument("--only", nargs="*", default=[])
    ap.add_argument("--out", default=None, help="write every row as JSON here")
    args = ap.parse_args()
    if args.rays < 1 or any(not s > 0 for s in args.scales):
        ap.error("--rays must be >= 1 and every --scales factor > 0")
    if args.ratio is None and not args.calibration:
        args.calibration = "calibration.json"
    if args.calibration:
        if not Path(args.calibration).exists():
            ap.error(f"{args.calibration}: no such calibration file (run `calibrate run`, or pass --ratio R)")
        source = P.constants_from_args(argparse.Namespace(calibration=args.calibration, ratio=None),
                                       rays=args.ray_set)
    else:
        source = dict(ratio=args.ratio)
    names = scene_names(Path(args.meshes), only=args.only)
    print(f"constants: {args.calibration or f'r = {args.ratio}'}; {args.rays} isotropic rays a grid; "
          f"scales {' '.join(f'{s:g}' for s in args.scales)} of the planned L1 resolution")
    print(f"{'scene':24s} {'scale':>5s} {'resolution':>12s}  {'steps':>6s} {'tests':>6s} {'visits':>6s}  "
          f"{'tests/visit':>11s} {'R/occ':>6s} {'by distance':>11s}  {'changes (model, kernel)':>23s}")
    rows = []
    for name in names:
        scene = Scene.load(name)
        for r in measure_scene(scene, source, args.scales, args.rays):
            rows.append(r)
            e, kk, m = r["error"], r["kernel"], r["model"]
            tpv = "-" if kk["tests_per_visit"] is None else f"{kk['tests_per_visit']:.1f}"
            print(f"{Path(r['scene']).name[:24]:24s} {r['scale']:5.2f} {'x'.join(map(str, r['resolution'])):>12s}  "
                  f"{_pct(e['steps'])} {_pct(e['tests'])} {_pct(e['visits'])}  {tpv:>11s} "
                  f"{m['refs_per_occupied']:6.1f} {_pct(e['tests_by_distance']):>11s}  "
                  f"{m['changes']:11.2f} {kk['changes']:11.2f}", flush=True)
    print("\nmedian |model / kernel - 1| over every grid (and the worst):")
    for key, label in (("steps", "steps"), ("tests", "tests"), ("visits", "occupied cells entered"),
                       ("tests_by_distance", "tests by the distance")):
        v = np.array([abs(r["error"][key]) for r in rows if r["error"][key] is not None])
        if v.size:
            print(f"  {label:26s} {100 * np.median(v):6.1f}%  (worst {100 * v.max():.0f}%)")
    v = np.array([abs(r["error"]["changes"]) for r in rows])
    if v.size:  # a scan's rays make 1.6-1.8 at every size, a coarse cylinder's none: absolute, per ray
        print(f"  {'changes of occupancy':26s} {np.median(v):6.2f} a ray  (worst {v.max():.2f})")
    if args.out:
        Path(args.out).write_text(json.dumps(P.json_ready(dict(rows=rows)), indent=1))
    sys.stdout.flush()


if __name__ == "__main__":
    main()
