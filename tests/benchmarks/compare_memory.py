"""Benchmark read-out: a compare run's measured times against the constants' price, by grid size.

    python tests/benchmarks/compare_memory.py COMPARE.json [--calibration FILE] [--ray-set isotropic|camera]

Reads the JSON ``tests/benchmarks/compare_all.py --out`` writes.  Every measured grid
of every sweep carries the kernel's own counts per ray (steps, tests, subgrids,
occupied cells entered); priced with the calibration's constants, they give the time
the cost model would give with exact counts.  The ratio measured / priced is then the
part of the time the constants miss, and this prints it by the grid's size in bytes
(bins doubling from 1 MiB), and per scene its slope against the size: ``d ln(ratio) /
d log2(bytes)``, over the single-level grids of the sweep.

The constants are the compare's own (its JSON's ``constants`` per scene) when they are
complete, T_visit included; with ``--calibration`` (the file the compare ran with),
that file's fit of ``--ray-set`` instead.  A calibrated T_hit is priced for the share
of the sweep's rays that hit (the JSON's ``hits_per_ray``; 0 in files without it).  Reads files only: nothing is timed.
Not a test (docs/compare.md, "What the constants miss: the grid's size").
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from calibrate import predict as P

BIN_EDGES_MIB = (0, 1, 2, 4, 8, 16, 32, 64, math.inf)
PRICED = ("t_setup", "t_step", "t_int", "t_sub", "t_visit")
#: Priced when present: T_hit, times the share of the sweep's rays that hit (``hits_per_ray``).
OPTIONAL = ("t_hit",)


def _constants(scene: dict, override: dict | None) -> dict:
    if override is not None:
        return override
    c = scene.get("constants") or {}
    missing = [n for n in PRICED if c.get(n) is None]
    if missing:
        raise SystemExit(f"{scene.get('scene')}: the compare's constants lack {', '.join(missing)} (a file written "
                         "before they were all recorded): pass --calibration FILE, the calibration it ran with")
    return {n: float(c[n]) for n in PRICED} | {n: float(c.get(n) or 0.0) for n in OPTIONAL}


def rows_of(compare: dict, override: dict | None) -> list[dict]:
    """One row per measured grid: scene, levels, bytes, measured and priced ns per ray."""
    out = []
    for scene in compare.get("scenes", []):
        k = _constants(scene, override)
        for p in scene.get("points", []):
            if p.get("median_ns") is None or p.get("memory_bytes") is None:
                continue
            priced = (k["t_setup"] + k["t_step"] * p["steps"] + k["t_int"] * p["tests"]
                      + k["t_sub"] * p.get("subgrids", 0.0) + k["t_visit"] * p.get("visits", 0.0)
                      + k.get("t_hit", 0.0) * float(scene.get("hits_per_ray") or 0.0))
            out.append(dict(scene=scene["scene"], levels=int(p.get("levels", 1)), bytes=int(p["memory_bytes"]),
                            measured=float(p["median_ns"]), priced=float(priced)))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("compare", help="the JSON compare_all.py wrote (--out)")
    ap.add_argument("--calibration", default=None, help="price with this calibration's constants instead")
    ap.add_argument("--ray-set", default="isotropic", choices=("isotropic", "camera"))
    args = ap.parse_args()
    path = Path(args.compare)
    try:
        compare = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise SystemExit(f"{path}: cannot read a compare run's JSON ({exc})") from None
    override = None
    if args.calibration:
        k = P.load_calibration_constants(args.calibration, rays=args.ray_set)
        override = {n: float(getattr(k, n)) for n in PRICED + OPTIONAL}
    rows = rows_of(compare, override)
    if not rows:
        raise SystemExit(f"{path}: no measured grids")
    mib = np.array([r["bytes"] for r in rows]) / 2.0 ** 20
    ratio = np.array([r["measured"] / r["priced"] for r in rows])
    print(f"{len(rows)} measured grids of {len({r['scene'] for r in rows})} scenes; measured / priced with the "
          f"{'calibration ' + args.calibration if override else 'compare'}'s constants and the kernel's counts")
    print(f"{'grid MiB':>12s} {'grids':>6s} {'median':>7s} {'25%':>6s} {'75%':>6s}")
    for lo, hi in zip(BIN_EDGES_MIB[:-1], BIN_EDGES_MIB[1:]):
        m = (mib >= lo) & (mib < hi)
        if m.any():
            q = np.percentile(ratio[m], [50, 25, 75])
            label = f"{lo:g}-{hi:g}" if math.isfinite(hi) else f">= {lo:g}"
            print(f"{label:>12s} {int(m.sum()):6d} {q[0]:7.2f} {q[1]:6.2f} {q[2]:6.2f}")
    print(f"\n{'scene (single-level grids)':28s} {'MiB':>13s} {'ratio at smallest':>17s} {'at largest':>10s} "
          f"{'d ln(ratio)/d log2(bytes)':>26s}")
    for name in dict.fromkeys(r["scene"] for r in rows):
        m = np.array([r["scene"] == name and r["levels"] == 1 for r in rows])
        if m.sum() < 3:
            continue
        x, y = np.log2(mib[m]), np.log(ratio[m])
        slope = np.polyfit(x, y, 1)[0] if np.ptp(x) > 0 else float("nan")
        print(f"{Path(name).name[:28]:28s} {mib[m].min():5.1f}-{mib[m].max():6.1f} {ratio[m][np.argmin(x)]:17.2f} "
              f"{ratio[m][np.argmax(x)]:10.2f} {slope:+26.3f}")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
