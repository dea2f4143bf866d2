"""Benchmark: grid build rate (references per second) with one and two build threads.

    python tests/benchmarks/build_speed.py [--repeats K] [--triangles N ...] [MESH ...]

For each scene, the recommended uniform grid (analytic plan, r = 1, as
``calibrate bench --scale`` plans it) is built ``1 + K`` times per thread count
in a fresh order: the first build of each (for the first scene, the first time
the process touches that much memory, as a user's one build does; a later scene's
may reuse the mappings gc_grid_free keeps) and the median of the others are
printed, as wall time and M references/s.  The meshes default to the largest
of ../shared/meshes when that folder is beside the checkout; the built-in
sphere is built at each ``--triangles`` count twice: with its lattice vertex
order (faces read their corners from all over the vertex array) and renumbered
in the order the faces first use them (as most exporters write them).
``calibrate bench --scale`` pins itself to one core, so its build column is the
one-thread build; this benchmark is not pinned.
Not a test: the goal (at least 20 M references/s) is read off the figures.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from compare_all import MESHES as SHARED_MESHES  # noqa: E402
from predict_speed import first_use_order  # noqa: E402

from calibrate import Scene  # noqa: E402
from calibrate._grid import Grid  # noqa: E402
from calibrate.predict import predict  # noqa: E402
from calibrate.scenes import sphere_mesh  # noqa: E402

DEFAULT_MESHES = ("stanford_bunny_69k.obj", "armadillo_86k.obj", "sponza_dabrovic_66k.obj")
THREADS = (1, 2)


def scenes(args):
    paths = args.meshes or [SHARED_MESHES / m for m in DEFAULT_MESHES if (SHARED_MESHES / m).exists()]
    for p in paths:
        yield Path(p).name, Scene.load(str(p))
    for n in args.triangles:
        v, f = sphere_mesh(n)
        yield f"sphere {len(f):,} (lattice order)", Scene(v, f, name="sphere")
        v2, f2 = first_use_order(v, f)
        yield f"sphere {len(f):,} (first-use order)", Scene(v2, f2, name="sphere")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("meshes", nargs="*", help="mesh files (default: the largest of ../shared/meshes)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--triangles", type=int, nargs="*", default=[1_000_000])
    args = ap.parse_args()
    print(f"{'scene':36s} {'resolution':>12s} {'references':>11s}  "
          + "  ".join(f"{t} thread{'s' if t > 1 else ''}: first / median s (M refs/s)" for t in THREADS))
    for name, scene in scenes(args):
        res = predict(scene, ratio=1.0, fidelity="analytic", levels="1")["levels"][0]["resolution"]
        times = {t: [] for t in THREADS}
        refs = None
        for k in range(1 + args.repeats):
            for t in (THREADS if k % 2 == 0 else THREADS[::-1]):
                t0 = time.perf_counter()
                g = Grid.uniform(scene, res, threads=t)
                times[t].append(time.perf_counter() - t0)
                refs = g.info["n_refs"]
                del g
        cols = []
        for t in THREADS:
            first, med = times[t][0], statistics.median(times[t][1:])
            cols.append(f"{first:.4f} / {med:.4f} ({refs / first / 1e6:5.1f} / {refs / med / 1e6:5.1f})")
        print(f"{name:36s} {'x'.join(map(str, res)):>12s} {refs:>11,}  " + "   ".join(cols), flush=True)


if __name__ == "__main__":
    main()
