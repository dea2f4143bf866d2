"""Benchmark: a big grid's time against the memory term charged on the whole grid and on what rays read.

    python tests/benchmarks/reached_memory.py [--calibration FILE (default calibration.json)]
        [--scene cylinder19996] [--rays 16384] [--out rows.json] RESOLUTION ...

For each resolution (``NXxNYxNZ``) of one scene (a built-in name or a mesh file): the
time a ray measured (``calibrate.sweep.sweep``, every grid in one interleaved sweep on
the same isotropic rays), the instrumented kernel's steps, tests and occupied cells
entered, and the calibration's price of those counts twice: with the memory term as
the cost model charges it (``1 - C/F`` of the lines missed, F the whole grid) and with
the share of the bytes read that misses when each cell is weighed by how often the
rays enter it (:func:`calibrate.reach.read_miss_fraction`, Che's approximation), the
rates counted on ``--rate-rays`` rays (more than are timed: a cell a batch enters once has
its rate known to a factor of two at best, and the time of a batch of 16,384 rays is
already a stream's, docs/calibration.md).
Only the memory term differs between the two prices; the counts are the kernel's, so
the gap to the measured time is the constants' and the memory term's, not the count
model's.

Not a test: it shows where the whole grid is the wrong footprint (docs/calibration.md,
"What rays read of a big grid").  Default: the long cylinder's grids of that section.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from calibrate import Scene
from calibrate import predict as P
from calibrate import sweep as S
from calibrate._grid import Grid
from calibrate.compare import DEFAULT_RAY_COUNT
from calibrate.rays import isotropic
from calibrate.reach import read_miss_fraction
from models.memory import STEP_LINES, TEST_LINES, VISIT_LINES

RAY_SEED = 11
DEFAULT_RESOLUTIONS = ["65x65x12", "65x65x24", "65x65x48", "65x65x105", "96x96x12", "96x96x24", "96x96x48",
                       "96x96x105", "130x130x12", "130x130x48", "106x106x170"]


def _resolution(text: str):
    try:
        res = tuple(int(v) for v in text.lower().split("x"))
    except ValueError:
        res = ()
    if len(res) != 3 or min(res) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: a resolution is three whole numbers >= 1, e.g. 65x65x12")
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("resolutions", nargs="*", type=_resolution, help=f"default: {' '.join(DEFAULT_RESOLUTIONS)}")
    ap.add_argument("--calibration", default="calibration.json")
    ap.add_argument("--scene", default="cylinder19996", help="a built-in scene or a mesh file")
    ap.add_argument("--rays", type=int, default=DEFAULT_RAY_COUNT, help="isotropic rays (default: compare's)")
    ap.add_argument("--rate-rays", type=int, default=65536, help="isotropic rays the cells' read rates are counted on")
    ap.add_argument("--out", default=None, help="write the rows as JSON here")
    args = ap.parse_args()
    if args.rays < 1 or args.rate_rays < 1:
        ap.error("--rays and --rate-rays must be >= 1")
    if not Path(args.calibration).exists():
        ap.error(f"{args.calibration}: no such calibration file (run `calibrate run`)")
    k = P.load_calibration_constants(args.calibration, "isotropic")
    if not k.has_memory:
        ap.error(f"{args.calibration}: its isotropic fit has no memory term (T_mem) to compare")
    try:
        scene = Scene.load(args.scene)
    except (ValueError, OSError) as exc:
        ap.error(str(exc))
    resolutions = args.resolutions or [_resolution(r) for r in DEFAULT_RESOLUTIONS]
    o, d = isotropic(scene.box_lo, scene.box_hi, args.rays, RAY_SEED)
    ro, rd = isotropic(scene.box_lo, scene.box_hi, args.rate_rays, RAY_SEED + 1)
    print(f"{scene.name}: {args.rays} isotropic rays timed, {args.rate_rays} counted for the read rates; constants {args.calibration} (isotropic fit, "
          f"T_mem {k.t_mem:.3g} ns a line, C = {k.cache_bytes / 2 ** 20:g} MiB); timing {len(resolutions)} grids",
          file=sys.stderr)
    timed = S.sweep(scene, [S.GridSpec("uniform", (r,)) for r in resolutions], (o, d))
    print(f"{'resolution':>12s} {'MiB':>6s} {'read MiB':>8s} {'measured':>9s} {'whole grid':>16s} "
          f"{'what rays read':>16s}  steps  tests")
    rows = []
    for res, row in zip(resolutions, timed):
        if row.get("skipped"):
            print(f"{'x'.join(map(str, res)):>12s}  skipped: {row['skipped']}")
            continue
        reach = read_miss_fraction(Grid.uniform(scene, res), ro, rd, k.cache_bytes)
        # the occupied cells entered and the changes of occupancy, as T_visit prices them
        steps, tests, visits = row["steps"], row["tests"], row["visits"] + row["changes"]
        # the lines a ray reads (models/memory.py)
        lines = STEP_LINES * steps + VISIT_LINES * visits + TEST_LINES * tests
        base = k.cost(steps, tests, 0.0, 0.0, visits)
        whole = base + k.t_mem * reach["whole"] * lines
        read = base + k.t_mem * reach["weighted"] * lines
        t = row["median_ns"]
        print(f"{'x'.join(map(str, res)):>12s} {reach['memory_bytes'] / 2 ** 20:6.1f} {reach['read_bytes'] / 2 ** 20:8.1f} "
              f"{t:7.0f}ns {whole:7.0f} ({100 * (whole / t - 1):+4.0f}%) {read:7.0f} ({100 * (read / t - 1):+4.0f}%) "
              f"{steps:6.1f} {tests:6.1f}", flush=True)
        rows.append(dict(resolution=list(res), measured_ns=t, priced_whole_ns=whole, priced_read_ns=read,
                         miss_whole=reach["whole"], miss_read=reach["weighted"], memory_bytes=reach["memory_bytes"],
                         read_bytes=reach["read_bytes"], steps=steps, tests=tests, visits=visits))
    if args.out:
        Path(args.out).write_text(json.dumps(dict(scene=scene.name, rays=args.rays, rate_rays=args.rate_rays,
                                                  rows=rows), indent=1))


if __name__ == "__main__":
    main()
