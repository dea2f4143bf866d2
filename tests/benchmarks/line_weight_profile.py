"""Benchmark: how well a calibration's timings fit with a test's (step's, occupied cell's) lines weighted otherwise.

    python tests/benchmarks/line_weight_profile.py CALIBRATION.json ... [--weights W ...] [--scene S ...]
        [--term test|step|visit]

The memory term counts ``STEP_LINES`` (1) a cell step, ``VISIT_LINES`` (2) an occupied
cell entered or a change of occupancy and ``TEST_LINES`` (72/64) a triangle test of the
lines a ray fetches from beyond the cache (models/memory.py).
The lines of one cell's packs come one after another and the hardware's prefetchers
can fetch them ahead, so a test may cost less than 72/64 of a step's dependent load.
For each weight W here, every calibration given is scored and refitted with
``models.memory.TEST_LINES = W`` (with ``--term step``, ``STEP_LINES = W``: since the
kernels read a step's record only in occupied cells, a step fetches less than a line;
with ``--term visit``, ``VISIT_LINES = W``):

- ``score``: the sum over ray sets of the maximum log posterior of the fitted
  configurations (the held-back ones left out), as ``calibrate run`` scores its
  candidate cache sizes (calibrate.run.select_cache), against the file's cache size;
  the weight the timings favour scores highest, and two weights within a few units
  are not told apart;
- the refit's isotropic r with its 95% half-width, and the held-back and
  cross-validated errors (``calibrate fit``, calibrate.run.refit_calibration);
- with ``--scene``, the uniform grid the refit plans for each scene (isotropic fit, as
  ``calibrate predict`` plans it).

Nothing is timed: the calibrations' stored measurements are fitted again.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import models.memory as memory  # noqa: E402
from calibrate import calfile  # noqa: E402
from calibrate import run as R  # noqa: E402
from calibrate._grid import Scene  # noqa: E402
from calibrate._io import UserError  # noqa: E402
from calibrate.predict import constants_from_args, predict  # noqa: E402

DEFAULT_WEIGHTS = (0.25, 0.5, 0.75, 72 / 64, 1.5)
#: The weight each term names: the models.memory constant it patches.
TERMS = {"test": "TEST_LINES", "step": "STEP_LINES", "visit": "VISIT_LINES"}


def fitted_timings(cal: dict) -> tuple[list, dict]:
    """(the calibration's measurements with the host's slowdown divided out, the in-context
    priors its isolating suites give); neither depends on the memory count, so once a file."""
    recs = calfile.apply_drift(cal["measurements"])
    isolated, _ = R._isolated_fit(recs, 0)
    return recs, R._priors(isolated)


def score(recs: list, priors: dict, cache: int) -> float:
    """Maximum log posterior of the fitted configurations with the memory count as
    models.memory stands now, against ``cache`` bytes, summed over ray sets
    (calibrate.run.select_cache's score)."""
    _, scores = R.select_cache(recs, [cache], 0, priors)
    return scores[cache]


def plan_source(cal: dict, folder: str) -> dict:
    """predict's constants and samples of a calibration's isotropic fit, loaded from a file as
    ``calibrate predict --calibration`` loads them."""
    path = Path(folder) / "refit.json"
    path.write_text(json.dumps(cal))
    return constants_from_args(argparse.Namespace(calibration=str(path), ratio=None), rays="isotropic")


def half_width(c: dict) -> float:
    r = c["ratio"]
    return 100 * (r["ci95"][1] - r["ci95"][0]) / 2 / r["median"]


def pct(x) -> str:
    """A share as a percentage, or '-' where the file has none (no held-back configurations)."""
    return "-" if x is None else f"{100 * x:.1f}%"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("calibrations", nargs="+")
    ap.add_argument("--weights", type=float, nargs="+", default=list(DEFAULT_WEIGHTS),
                    help="lines a test (a step, an occupied cell: --term) counts (default: %(default)s)")
    ap.add_argument("--term", choices=tuple(TERMS), default="test", help="the count weighted (default: test)")
    ap.add_argument("--scene", action="append", default=[], help="a built-in scene or mesh to plan (repeatable)")
    args = ap.parse_args()
    bad = [w for w in args.weights if not (math.isfinite(w) and w >= 0)]
    if bad:
        ap.error(f"--weights must be finite and >= 0, got {bad[0]!r}")
    try:
        scenes = [Scene.load(s) for s in args.scene]
    except (ValueError, OSError) as exc:
        raise UserError(str(exc)) from None
    name = TERMS[args.term]
    saved = getattr(memory, name)
    folder = tempfile.TemporaryDirectory()
    try:
        for path in args.calibrations:
            cal = calfile.load(path)
            cache = calfile.cache_bytes_of(cal)
            if cache is None:
                print(f"{path}: no cache size recorded, so no memory term: the weight changes nothing")
                continue
            print(f"{path}: cache {cache / 2 ** 20:g} MiB")
            recs, priors = fitted_timings(cal)
            print(f"  {'lines a ' + args.term:>12} {'score':>8} {'isotropic r':>18} {'held back':>10} {'cross-val':>10}"
                  + "".join(f"  {s.name[:22]:>22}" for s in scenes))
            for w in args.weights:
                setattr(memory, name, float(w))
                new, _ = R.refit_calibration(cal, seed=0)
                iso = new.get("by_rays", {}).get("isotropic", new)["constants"]
                meta = new["meta"]
                source = plan_source(new, folder.name)
                plans = ["x".join(map(str, predict(s, levels="1", **source)["levels"][0]["resolution"]))
                         for s in scenes]
                print(f"  {w:12.3f} {score(recs, priors, cache):8.1f} {iso['ratio']['median']:8.3f} +-{half_width(iso):5.1f}%"
                      f" {pct(meta.get('holdout_mare')):>10} {pct(meta.get('cv_mare')):>10}"
                      + "".join(f"  {p:>22}" for p in plans), flush=True)
    finally:
        setattr(memory, name, saved)
        folder.cleanup()


if __name__ == "__main__":
    try:
        main()
    except UserError as exc:  # a bad file or scene name: said, no traceback
        sys.exit(f"line_weight_profile.py: {exc}")
