"""Benchmark: `calibrate compare` over the built-in scenes and the real meshes.

    python tests/benchmarks/compare_all.py [--ratio R | --calibration FILE (default calibration.json)]
        [--ray-set isotropic|camera] [--out results.json]
        [--plot figure.png --plot-scenes NAME ...] [--skip NAME ...] [--only NAME ...]

Prints, per scene, the penalty of the prediction and of each baseline against the
measured best, then the median and worst penalty of each over all scenes.  Results
are written to ``--out`` after every scene (a long run can be read while it goes).
Real meshes are found in ../shared/meshes beside the checkout; absent, only the
built-in scenes run.  Meshes above ``--big`` triangles get ``--big-rays`` rays per
batch instead of ``--rays`` (said in the output).  Not a test: the goals (median
penalty at most 1%, worst at most 3%, a lower median than every baseline) are read off
the figures.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from calibrate import Scene
from calibrate.compare import DEFAULT_POINTS, DEFAULT_RAY_COUNT, REFINE_ROUNDS, compare_scene, plot, summarise
from calibrate.sweep import SWEEP_BUILDS, SWEEP_ROUNDS
from calibrate.predict import constants_from_args, resolve_constants
from calibrate.scenes import builtin_names

MESHES = Path(__file__).resolve().parents[3] / "shared" / "meshes"
MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off")


def _pct(x):
    return "      -" if x is None else f"{100 * x:+7.1f}"


def _ci(r):
    ci = r.get("penalty_ci95")
    return f" [{100 * ci[0]:+.1f}, {100 * ci[1]:+.1f}]" if ci else ""


def scene_names(meshes: Path, only=(), skip=()) -> list[str]:
    """The built-in scenes, then the meshes in ``meshes`` (said when the folder is absent), less
    those ``skip`` names, only those ``only`` names when it names any (file names or paths)."""
    names = list(builtin_names())
    if meshes.is_dir():
        names += sorted(str(p) for p in meshes.iterdir() if p.suffix.lower() in MESH_SUFFIXES)
    else:
        print(f"real meshes absent ({meshes}); built-in scenes only")
    names = [n for n in names if Path(n).name not in skip and n not in skip]
    if only:
        names = [n for n in names if Path(n).name in only or n in only]
    return names


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    src = ap.add_mutually_exclusive_group()
    src.add_argument("--ratio", type=float, default=None)
    src.add_argument("--calibration", default=None)
    ap.add_argument("--meshes", default=str(MESHES), help="directory of real meshes (default ../shared/meshes)")
    ap.add_argument("--levels", default="auto")
    ap.add_argument("--fidelity", default="analytic")
    ap.add_argument("--points", type=int, default=DEFAULT_POINTS)
    ap.add_argument("--rays", type=int, default=DEFAULT_RAY_COUNT,
                    help=f"rays per batch (default {DEFAULT_RAY_COUNT}, compare's own)")
    ap.add_argument("--ray-set", default="isotropic", choices=("isotropic", "camera"),
                    help="the rays traced; the calibration's fit of that set alone when it has one")
    ap.add_argument("--big", type=int, default=50_000, help="triangles above which --big-rays is used")
    ap.add_argument("--big-rays", type=int, default=DEFAULT_RAY_COUNT,
                    help="rays per batch of the scenes above --big triangles (default the same: fewer rays, "
                         "traced again and again, keep their grid's lines cached and time it too fast)")
    ap.add_argument("--rounds", type=int, default=SWEEP_ROUNDS, help="timed values per grid")
    ap.add_argument("--builds", type=int, default=SWEEP_BUILDS, help="builds of every grid the values are spread over")
    ap.add_argument("--no-prime", action="store_true", help="no untimed call before each value")
    ap.add_argument("--refine-rounds", type=int, default=REFINE_ROUNDS,
                    help="values added to the grids that decide the penalties (0: none)")
    ap.add_argument("--out", default="compare_all.json")
    ap.add_argument("--plot", default=None)
    ap.add_argument("--plot-scenes", nargs="*", default=[])
    ap.add_argument("--skip", nargs="*", default=[])
    ap.add_argument("--only", nargs="*", default=[])
    args = ap.parse_args()
    if args.ratio is None and not args.calibration:
        args.calibration = "calibration.json"  # a calibration belongs to its kernels: no built-in r
    if args.calibration:
        source = constants_from_args(argparse.Namespace(calibration=args.calibration, ratio=None), rays=args.ray_set)
        k = resolve_constants(**source)
    else:
        source = dict(ratio=args.ratio)
    names = scene_names(Path(args.meshes), only=args.only, skip=args.skip)
    fit = "" if "ratio" in source else f" ({source['constants'].get('fitted_on', 'pooled')} fit, r = {k.ratio:.3f})"
    print(f"source: {source if 'ratio' in source else args.calibration}{fit}; {args.ray_set} rays; "
          f"levels {args.levels}; fidelity "
          f"{args.fidelity}; "
          f"{args.points} points per depth; {args.rays} rays ({args.big_rays} above {args.big:,} triangles); "
          f"{args.rounds} values per grid over {args.builds} builds{', unprimed' if args.no_prime else ''}, "
          f"{args.refine_rounds} more for the grids that decide the penalties")
    results = []
    for name in names:
        scene = Scene.load(name)
        n_rays = args.big_rays if scene.n_triangles > args.big else args.rays
        t0 = time.monotonic()
        try:
            r = compare_scene(scene, levels=args.levels, fidelity=args.fidelity, points=args.points,
                              ray_count=n_rays, rounds=args.rounds, builds=args.builds,
                              prime=not args.no_prime, rays=args.ray_set, refine_rounds=args.refine_rounds,
                              **source)
        except ValueError as exc:  # e.g. the predicted grid does not fit the sweep's memory budget
            print(f"{scene.name:28s} skipped: {exc}", flush=True)
            continue
        r["wall_s"] = time.monotonic() - t0
        results.append(r)
        base = "  ".join(f"{n} {_pct(b['penalty'])}" for n, b in r["baselines"].items())
        print(f"{r['scene']:28s} {r['triangles']:>7,} tri  L{r['predicted_levels']} pred "
              f"{'x'.join(map(str, r['predicted_resolution'])):>12s}  best L{r['best_measured_levels']} "
              f"{'x'.join(map(str, r['best_measured_resolution'])):>12s}  penalty {_pct(r['penalty'])}%{_ci(r)}  | {base}"
              f"  ({r['wall_s']:.0f} s, {n_rays} rays)", flush=True)
        Path(args.out).write_text(json.dumps(dict(scenes=results, summary=summarise(results)), indent=1))
    s = summarise(results)
    print("\npenalty over scenes (%):      median    worst")
    print(f"  {'predicted':26s} {_pct(s['predicted']['median'])} {_pct(s['predicted']['worst'])}")
    if s["predicted"]["worst_sure"] is not None:
        print(f"  {'(the lower end of a 95% interval)':26s}         {_pct(s['predicted']['worst_sure'])}  "
              f"({s['predicted']['worst_sure_scene']})")
    for n, b in s["baselines"].items():
        print(f"  {n:26s} {_pct(b['median'])} {_pct(b['worst'])}")
    if args.plot:
        chosen = [r for r in results if r["scene"] in args.plot_scenes] or results[:2]
        plot(chosen, Path(args.plot))
        print(f"plot of {', '.join(r['scene'] for r in chosen)} written to {args.plot}")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
