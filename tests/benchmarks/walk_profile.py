"""Profile target: one batch of a built-in scene's rays through one uniform grid, for callgrind.

    valgrind --tool=callgrind --toggle-collect=gc_bench_intersect --branch-sim=yes --cache-sim=yes \\
        --callgrind-out-file=OUT python tests/benchmarks/walk_profile.py SCENE RESOLUTION [--rays N]
    callgrind_annotate --auto=yes --show=Ir,Bcm,D1mr OUT

Builds ``SCENE`` (a built-in scene) at ``RESOLUTION`` (e.g. 23x23x117) and traces
``--rays`` isotropic rays (the in-context suite's seed) once through the timed twin
(``gc_bench_intersect``, the code ``calibrate run`` times).  With
``--toggle-collect=gc_bench_intersect`` callgrind counts only that call: the
instructions, simulated branch mispredictions and level-1 data misses per ray of
one traversal, by source line.  Instruction and misprediction counts are the same
on every run (no clock is read); they say where a scene's time goes when its
timings and the four-constant cost disagree (docs/calibration.md, "One T_step for
every scene").  Valgrind needs an instruction set it emulates: the kernels choose
theirs at run time (AVX2 here).
"""

from __future__ import annotations

import argparse
import sys

from calibrate import suites
from calibrate._grid import Grid, Scene
from calibrate._io import UserError


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", help="a built-in scene, e.g. cylinder1996")
    ap.add_argument("resolution", help="cells per axis, e.g. 23x23x117")
    ap.add_argument("--rays", type=int, default=4096)
    args = ap.parse_args(argv)
    try:
        res = tuple(int(x) for x in args.resolution.lower().split("x"))
        if len(res) != 3 or min(res) < 1:
            raise ValueError
    except ValueError:
        print(f"error: resolution must be three whole numbers >= 1 like 23x23x117, got {args.resolution!r}",
              file=sys.stderr)
        return 2
    if args.rays < 1:
        print(f"error: --rays must be >= 1, got {args.rays}", file=sys.stderr)
        return 2
    try:
        scene = Scene.builtin(args.scene)
    except (UserError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    grid = Grid.uniform(scene, res, "watertight")
    o, d = suites._rays(scene, "isotropic", 1)
    run = grid.timed_batch(o[: args.rays], d[: args.rays], clock="wall")
    run(1)
    print(f"{args.scene} {args.resolution}: {min(args.rays, o.shape[0])} rays traced once")
    return 0


if __name__ == "__main__":
    sys.exit(main())
