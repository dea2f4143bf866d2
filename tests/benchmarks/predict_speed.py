"""Benchmark: time to predict, per fidelity, for a mesh of about a million triangles.

    python tests/benchmarks/predict_speed.py [--triangles N] [--repeats K] [--vertex-order lattice|first-use]

"After loading" means from a Scene already in memory (the mesh read and
validated) to the recommendation: the scene statistics are part of the time.
Each fidelity gets a fresh Scene per repeat so nothing is cached between them;
the minimum and median over repeats are printed (a shared machine is noisy),
with the median CPU time of the process (all its threads): on a loaded machine
the wall time waits for cores, the CPU time much less.
The compiled statistics run the watertightness test in a second thread beside
the sums; the "1 thread" rows run them one after the other (on a loaded
machine the second thread may find no free core).
The built-in sphere numbers its vertices by lattice position, so the faces read
their corners from all over the vertex array; ``--vertex-order first-use``
renumbers them in the order the faces first use them (as most mesh exporters
and re-meshers write them), same geometry, the same statistics.
Not a test: the goal (analytic at most 50 ms) is read off the figures.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from calibrate import Scene
from calibrate._grid import compiled_scene_stats
from calibrate.predict import predict
from calibrate.scenes import sphere_mesh
from models.stats import scene_stats

CASES = [("statistics, numpy reference", None, None), ("statistics, compiled", "stats", None),
         ("statistics, compiled, 1 thread", "stats", "1 thread"), ("paper", "paper", "1"),
         ("analytic, 1 level", "analytic", "1"), ("analytic, 1 level, 1 thread", "analytic", "1 thread"),
         ("analytic, auto levels", "analytic", "auto"), ("simulated, 1 level", "simulated", "1")]


def first_use_order(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The same mesh with its vertices renumbered in the order the faces first use them."""
    used, first = np.unique(f.ravel(), return_index=True)
    order = used[np.argsort(first)]  # old index of each new vertex
    new_of_old = np.empty(len(v), dtype=f.dtype)
    new_of_old[order] = np.arange(len(order), dtype=f.dtype)
    return np.ascontiguousarray(v[order]), new_of_old[f]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--triangles", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--skip", nargs="*", default=[], help="case names to skip (e.g. simulated)")
    ap.add_argument("--vertex-order", choices=("lattice", "first-use"), default="lattice")
    ap.add_argument("--calibration", default=None,
                    help="predict with this calibration's isotropic constants (with T_mem or T_visit the "
                         "analytic plan also searches the resolution) instead of --ratio 1")
    args = ap.parse_args()
    src = dict(ratio=1.0)
    if args.calibration:
        from calibrate.predict import constants_from_args

        src = constants_from_args(argparse.Namespace(calibration=args.calibration, ratio=None), rays="isotropic")
    v, f = sphere_mesh(args.triangles)
    if args.vertex_order == "first-use":
        v, f = first_use_order(v, f)
    print(f"mesh: displaced sphere, {len(f):,} triangles, {len(v):,} vertices, vertices in {args.vertex_order} order; "
          f"constants: {args.calibration or 'ratio 1'}")
    print(f"{'case':32s} {'min ms':>10s} {'median ms':>10s} {'cpu ms':>10s}")
    for label, fidelity, levels in CASES:
        if any(s in label for s in args.skip):
            continue
        times, cpu = [], []
        for _ in range(args.repeats if fidelity not in ("simulated",) and levels != "auto" else 1):
            scene = Scene(v, f, name="sphere-1M")
            t0, c0 = time.perf_counter(), time.process_time()
            if fidelity is None:
                scene_stats(scene.vertices, scene.faces)
            elif fidelity == "stats":
                _ = scene.stats if levels is None else compiled_scene_stats(scene.vertices, scene.faces, threads=1)
            else:
                if levels == "1 thread":  # the statistics the prediction reads, computed in one thread
                    scene._stats = compiled_scene_stats(scene.vertices, scene.faces, threads=1)
                predict(scene, fidelity=fidelity, levels="1" if levels == "1 thread" else levels, **src)
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        print(f"{label:32s} {1e3 * min(times):10.1f} {1e3 * statistics.median(times):10.1f} "
              f"{1e3 * statistics.median(cpu):10.1f}")


if __name__ == "__main__":
    main()
