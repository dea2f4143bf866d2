"""Benchmark: leave-one-out prediction error of a calibration's in-context batches.

`calibrate run` holds back a fifth of its configurations (16) and reports the
median error of their predicted batch times; with so few, that median moves by
a point or two from run to run.  Here every configuration is predicted in turn
by the posterior's maximum fitted to all the others of its ray set (no
sampling), with and without the memory term (docs/calibration.md, "The memory
effect"), and the median, mean and 90th percentile of the absolute relative
errors are printed.

    python tests/benchmarks/loo_holdout.py calibration.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from calibrate import calfile  # noqa: E402
from calibrate import fit as F  # noqa: E402


def loo_errors(recs: list, priors: dict, memory: bool) -> np.ndarray:
    """|predicted / measured - 1| of each record, predicted from the others' maximum a posteriori
    (cross-validation with one record per fold)."""
    design = calfile.design_from_measurements(recs, "in_context", include_held_back=True)
    if not memory:
        design.pop("misses", None)
    return F.cross_validated_errors(design, folds=len(recs), seed=0, priors=priors)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("calibration", nargs="?", default="calibration.json")
    args = ap.parse_args()
    cal = calfile.load(args.calibration)
    priors = {k: (float(v[0]), float(v[1])) for k, v in (cal["diagnostics"].get("priors") or {}).items()}
    recs = [m for m in cal["measurements"] if m["kind"] == "in_context" and m["values_ns"]]
    has_misses = all("misses" in m for m in recs)
    print(f"{args.calibration}: {len(recs)} in-context configurations; leave-one-out, maximum a posteriori")
    print(f"{'ray set':<12}{'model':<14}{'median':>8}{'mean':>8}{'p90':>8}")
    for ray_set in calfile.ray_sets(recs) or [None]:
        group = [m for m in recs if ray_set is None or m.get("ray_set") == ray_set]
        for memory in ((False, True) if has_misses else (False,)):
            e = 100 * loo_errors(group, priors, memory)
            print(f"{ray_set or 'all':<12}{'with T_mem' if memory else 'four terms':<14}"
                  f"{np.median(e):7.1f}%{e.mean():7.1f}%{np.percentile(e, 90):7.1f}%")


if __name__ == "__main__":
    main()
