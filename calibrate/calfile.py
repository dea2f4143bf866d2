"""The calibration file, ``calibration.json``: schema, validation, atomic save, re-fit.

Schema (version :data:`SCHEMA_VERSION`), one JSON object::

    {
      "schema_version": 1,
      "fingerprint":  {...},            # free-form host facts (calibrate.host.fingerprint)
      "constants": {                    # the in-context fit, used for predictions
        "t_setup_ns": {"median": m, "ci68": [lo, hi], "ci95": [lo, hi]},
        "t_step_ns":  {...},
        "t_int_ns":   {...},
        "t_sub_ns":   {...} or null,    # null when no measurement entered a subgrid
        "t_mem_ns":   {...} or null,    # the memory effect (models/memory.py); null or absent
                                        #   when not fitted (diagnostics.t_mem_skipped says why)
        "t_visit_ns": {...} or null,    # per occupied cell entered; null or absent when not
                                        #   fitted (diagnostics.t_visit_skipped says why)
        "t_hit_ns":   {...} or null,    # per ray that finds a hit; null or absent when not
                                        #   fitted (diagnostics.t_hit_skipped says why)
        "ratio":      {...}             # r = T_int / T_step, dimensionless
      },
      "isolated": {"t_step_ns": {"median": m, "ci95": [lo, hi]}, ...},
                                        # isolating microbenchmarks; may be partial or {}
      "samples": {"columns": ["t_setup_ns", ..., "extra_scatter"],
                  "values": [[...], ...]},   # thinned posterior, (S, C), ns (scatter: log units)
      "diagnostics": {...},             # acceptance, tau_steps, n_steps, converged, ...
      "measurements": [                 # every raw measurement
        {"kind": "isolated" | "in_context", "scene": str, "resolution": int | [..] | null,
         "intersector": str | null, "rays": int, "steps": int, "tests": int,
         "subgrids": int, "values_ns": [ns per batch, ...],
         "raw_values_ns": [...], "stamps_s": [...],  # optional: the values as timed and when
                                                 #   each ended (s); values_ns is then raw over
                                                 #   the host's common slowdown at that time
                                                 #   (protocol.drift_factors; apply_drift)
         "memory_bytes": int, "misses": float,   # optional: the grid's bytes, and the cache
                                                 #   lines its batch fetched from beyond the cache
         "visits": int,                          # optional: occupied cells entered (<= steps)
         "hits": int,                            # optional: rays that found a hit (<= rays)
         "changes": int,                         # optional: the walks' occupancy changes (<= steps;
                                                 #   Grid.count); with every record carrying
                                                 #   them, T_visit prices them with the visits
         ...extra keys kept}
      ],
      "meta": {...},                    # free-form (tool version, budget, wall time, ...);
                                        #   cache_bytes: the cache T_mem was measured against;
                                        #   line_weights: the lines a step, an occupied cell and
                                        #   a test were charged when T_mem was fitted
      "by_rays": {                      # optional: the same fit on one ray set's in-context
        "camera": {"constants": {...}, "samples": {...}, "diagnostics": {...}},
        "isotropic": {...}              #   measurements alone (coherent rays step for 1/2 to
      }                                 #   2/3 of the cost of incoherent ones); predictions for
    }                                   #   that ray set use it, others use ``constants``

Constants are in ns per unit (ray, cell step, triangle test, subgrid entry, cache line,
occupied cell entered, ray that hits).
:func:`load` validates everything and raises :class:`calibrate._io.UserError`
(a ``ValueError``) whose message names the file and the offending key.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from . import fit as _fit
from ._io import UserError, atomic_write_text

__all__ = [
    "SCHEMA_VERSION",
    "MEASUREMENT_KINDS",
    "SAMPLE_COLUMNS",
    "apply_drift",
    "constants_json",
    "design_from_measurements",
    "dumps",
    "fit_by_rays",
    "fit_for_rays",
    "from_fit",
    "load",
    "loads",
    "ray_sets",
    "refit",
    "samples_by_name",
    "save",
    "validate",
]

SCHEMA_VERSION = 1
MEASUREMENT_KINDS = ("isolated", "in_context")
CONSTANT_KEYS = _fit.CONSTANT_NAMES + (_fit.RATIO_NAME,)
# Constants a calibration must carry (t_sub_ns may be null or absent).
REQUIRED_CONSTANTS = ("t_setup_ns", "t_step_ns", "t_int_ns", _fit.RATIO_NAME)
SCATTER_COLUMN = "extra_scatter"
SAMPLE_COLUMNS = _fit.CONSTANT_NAMES + (SCATTER_COLUMN,)
REQUIRED_TOP_KEYS = ("schema_version", "fingerprint", "constants", "samples", "diagnostics", "measurements")
# Keys of one entry of the optional ``by_rays`` block (a fit on one ray set alone).
BY_RAYS_KEYS = ("constants", "samples", "diagnostics")
# Posterior samples stored in the file at most (evenly thinned beyond this):
# the 2.5th percentile of 2000 draws has a standard error of
# sqrt(0.025 * 0.975 / 2000) = 0.35 percentile points, ample for intervals.
MAX_STORED_SAMPLES = 2000
# Count fields of a measurement (batch totals); subgrids may be omitted (= 0).
COUNT_FIELDS = ("rays", "steps", "tests", "subgrids")
#: Counts a measurement may carry, each fitted (with its constant) when the timings call for it.
OPTIONAL_COUNT_FIELDS = ("misses", "visits", "hits")
#: The optional counts a calibration's fit takes by default: all, each fitted when the timings
#: call for it (:func:`fit_in_context`).  ``optional=("misses",)`` leaves T_visit and T_hit out,
#: as the fit did before the kernels' masked DDA step (docs/calibration.md, "Occupied cells").
DEFAULT_OPTIONAL_COUNTS = ("misses", "visits", "hits")


# ---------------------------------------------------------------------------
# Validation
# ---------------------------------------------------------------------------


def _fail(where: str, what: str):
    raise UserError(f"{where}: {what}" if where else what)


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _finite(x, where: str) -> float:
    if not _is_number(x):
        _fail(where, f"must be a number, got {type(x).__name__}")
    if not math.isfinite(x):
        _fail(where, f"must be finite, got {x}")
    return float(x)


def _object(x, where: str) -> Mapping:
    if not isinstance(x, dict):
        _fail(where, f"must be a JSON object, got {_json_type(x)}")
    return x


def _json_type(x) -> str:
    if x is None:
        return "null"
    if isinstance(x, bool):
        return "boolean"
    if isinstance(x, dict):
        return "object"
    if isinstance(x, list):
        return "array"
    if isinstance(x, str):
        return "string"
    if _is_number(x):
        return "number"
    return type(x).__name__


def _interval(x, where: str, median: float | None) -> tuple[float, float]:
    if not isinstance(x, list) or len(x) != 2:
        _fail(where, "must be a [low, high] pair")
    lo = _finite(x[0], f"{where}[0]")
    hi = _finite(x[1], f"{where}[1]")
    if lo > hi:
        _fail(where, f"low {lo:g} is above high {hi:g}")
    if lo < 0:
        _fail(where, f"negative bound {lo:g}; constants are positive")
    if median is not None and not (lo <= median <= hi):
        _fail(where, f"interval [{lo:g}, {hi:g}] does not contain the median {median:g}")
    return lo, hi


def _estimate(x, where: str, *, require_intervals: bool) -> None:
    obj = _object(x, where)
    if "median" not in obj:
        _fail(where, "missing key 'median'")
    med = _finite(obj["median"], f"{where}.median")
    if med <= 0:
        _fail(f"{where}.median", f"must be positive, got {med:g}")
    found = {}
    for key in ("ci68", "ci95"):
        if key in obj:
            found[key] = _interval(obj[key], f"{where}.{key}", med)
        elif require_intervals:
            _fail(where, f"missing key {key!r}")
    if "ci68" in found and "ci95" in found:
        (lo68, hi68), (lo95, hi95) = found["ci68"], found["ci95"]
        if lo95 > lo68 or hi95 < hi68:
            _fail(where, "ci95 does not contain ci68")


def _validate_constants(x, where: str, *, partial: bool) -> None:
    obj = _object(x, where)
    for key in obj:
        if key not in CONSTANT_KEYS:
            _fail(where, f"unknown constant {key!r} (known: {', '.join(CONSTANT_KEYS)})")
    if not partial:
        for key in REQUIRED_CONSTANTS:
            if key not in obj:
                _fail(where, f"missing key {key!r}")
            if obj[key] is None:
                _fail(f"{where}.{key}", "must not be null")
    for key, val in obj.items():
        if val is None:
            continue
        _estimate(val, f"{where}.{key}", require_intervals=not partial)


def _validate_samples(x, where: str, constants: Mapping) -> None:
    obj = _object(x, where)
    for key in ("columns", "values"):
        if key not in obj:
            _fail(where, f"missing key {key!r}")
    cols = obj["columns"]
    if not isinstance(cols, list) or not all(isinstance(c, str) for c in cols):
        _fail(f"{where}.columns", "must be an array of strings")
    if len(set(cols)) != len(cols):
        _fail(f"{where}.columns", "has duplicate names")
    for c in cols:
        if c not in SAMPLE_COLUMNS:
            _fail(f"{where}.columns", f"unknown column {c!r} (known: {', '.join(SAMPLE_COLUMNS)})")
    for key in ("t_setup_ns", "t_step_ns", "t_int_ns"):
        if key not in cols:
            _fail(f"{where}.columns", f"missing column {key!r}")
    for key in ("t_sub_ns", "t_mem_ns", "t_visit_ns", "t_hit_ns"):
        if constants.get(key) is not None and key not in cols:
            _fail(f"{where}.columns", f"missing column {key!r} although constants.{key} is set")
    values = obj["values"]
    if not isinstance(values, list) or not values:
        _fail(f"{where}.values", "must be a non-empty array of rows")
    n_cols = len(cols)
    arr = np.empty((len(values), n_cols))
    for i, row in enumerate(values):
        if not isinstance(row, list):
            _fail(f"{where}.values[{i}]", f"must be an array, got {_json_type(row)}")
        if len(row) != n_cols:
            _fail(
                f"{where}.values",
                f"shape mismatch: row {i} has {len(row)} values but there are {n_cols} columns",
            )
        for k, v in enumerate(row):
            arr[i, k] = _finite(v, f"{where}.values[{i}][{k}]")
    for k, c in enumerate(cols):
        bad = arr[:, k] < 0 if c == SCATTER_COLUMN else arr[:, k] <= 0
        if np.any(bad):
            i = int(np.flatnonzero(bad)[0])
            _fail(f"{where}.values[{i}][{k}]", f"{c} must be {'>= 0' if c == SCATTER_COLUMN else 'positive'}")


def _validate_resolution(x, where: str, depth: int = 0) -> None:
    if x is None or isinstance(x, str):
        return
    if _is_number(x):
        if not (float(x).is_integer() and x >= 1):
            _fail(where, f"must be a positive integer, got {x}")
        return
    if isinstance(x, list) and depth < 2 and x:
        for i, v in enumerate(x):
            _validate_resolution(v, f"{where}[{i}]", depth + 1)
        return
    _fail(where, "must be a positive integer, a non-empty array of them (per axis or per level), a string or null")


def _check_cells_stepped(obj, where, key, what, why):
    """An optional count of cells ``key`` of a measurement: a whole number >= 0, at most its steps."""
    if key not in obj:
        return
    v = _finite(obj[key], f"{where}.{key}")
    if v < 0 or not v.is_integer():
        _fail(f"{where}.{key}", f"must be a whole number of cells >= 0, got {v:g}")
    if _is_number(obj["steps"]) and v > obj["steps"]:
        _fail(f"{where}.{key}", f"{v:g} {what} but only {obj['steps']:g} cells stepped: {why}")


def _validate_measurement(m, where: str) -> None:
    obj = _object(m, where)
    for key in ("kind", "scene", "resolution", "intersector", "rays", "steps", "tests", "values_ns"):
        if key not in obj:
            _fail(where, f"missing key {key!r}")
    if obj["kind"] not in MEASUREMENT_KINDS:
        _fail(f"{where}.kind", f"must be one of {', '.join(MEASUREMENT_KINDS)}, got {obj['kind']!r}")
    if not isinstance(obj["scene"], str):
        _fail(f"{where}.scene", f"must be a string, got {_json_type(obj['scene'])}")
    if obj["intersector"] is not None and not isinstance(obj["intersector"], str):
        _fail(f"{where}.intersector", f"must be a string or null, got {_json_type(obj['intersector'])}")
    _validate_resolution(obj["resolution"], f"{where}.resolution")
    for key in COUNT_FIELDS:
        if key not in obj:
            continue
        v = _finite(obj[key], f"{where}.{key}")
        if v < 0:
            _fail(f"{where}.{key}", f"negative count {v:g}")
        if not v.is_integer():
            _fail(f"{where}.{key}", f"count must be a whole number, got {v:g}")
    if "memory_bytes" in obj:
        v = _finite(obj["memory_bytes"], f"{where}.memory_bytes")
        if v < 0 or not v.is_integer():
            _fail(f"{where}.memory_bytes", f"must be a whole number of bytes >= 0, got {v:g}")
    if "misses" in obj and _finite(obj["misses"], f"{where}.misses") < 0:
        _fail(f"{where}.misses", f"negative count {obj['misses']:g}")
    _check_cells_stepped(obj, where, "visits", "occupied cells entered", "visits are part of the steps")
    _check_cells_stepped(obj, where, "changes", "occupancy changes", "a change is a cell stepped into")
    if "hits" in obj:
        v = _finite(obj["hits"], f"{where}.hits")
        if v < 0 or not v.is_integer():
            _fail(f"{where}.hits", f"must be a whole number of rays >= 0, got {v:g}")
        if _is_number(obj["rays"]) and v > obj["rays"]:
            _fail(f"{where}.hits", f"{v:g} rays hit but the batch traced only {obj['rays']:g}")
    if obj["rays"] < 1:
        _fail(f"{where}.rays", "a batch must trace at least one ray")
    vals = obj["values_ns"]
    if not isinstance(vals, list):
        _fail(f"{where}.values_ns", f"must be an array of times in ns, got {_json_type(vals)}")
    for i, v in enumerate(vals):
        if _finite(v, f"{where}.values_ns[{i}]") < 0:
            _fail(f"{where}.values_ns[{i}]", f"negative time {v:g}")
    if ("raw_values_ns" in obj) != ("stamps_s" in obj):
        _fail(where, "raw_values_ns and stamps_s come together (the values as timed and when)")
    for key in ("raw_values_ns", "stamps_s"):
        if key not in obj:
            continue
        seq = obj[key]
        if not isinstance(seq, list):
            _fail(f"{where}.{key}", f"must be an array, got {_json_type(seq)}")
        if len(seq) != len(vals):
            _fail(f"{where}.{key}", f"has {len(seq)} entries for {len(vals)} values")
        for i, v in enumerate(seq):
            x = _finite(v, f"{where}.{key}[{i}]")
            if key == "raw_values_ns" and x <= 0:
                _fail(f"{where}.{key}[{i}]", f"time must be positive, got {x:g}")


def _validate_fit(obj: Mapping, prefix: str) -> None:
    """constants, samples and diagnostics of one fit (the file's own, or one of ``by_rays``)."""
    _validate_constants(obj["constants"], f"{prefix}constants", partial=False)
    _validate_samples(obj["samples"], f"{prefix}samples", obj["constants"])
    diag = _object(obj["diagnostics"], f"{prefix}diagnostics")
    if "converged" in diag and diag["converged"] is not True:
        _fail(f"{prefix}diagnostics.converged",
              "is not true: the posterior did not converge, so the constants are not a result")


def _has_t_mem(fit: Mapping) -> bool:
    c = fit.get("constants") if isinstance(fit, Mapping) else None
    return isinstance(c, Mapping) and c.get("t_mem_ns") is not None


def validate(cal: Any) -> dict:
    """Check a calibration object against the schema; return it unchanged.

    Raises UserError (a ValueError) naming the offending key, e.g.
    ``constants.t_step_ns.ci95: interval [..] does not contain the median ..``.
    """
    if not isinstance(cal, dict):
        _fail("", f"a calibration must be a JSON object, got {_json_type(cal)}")
    for key in REQUIRED_TOP_KEYS:
        if key not in cal:
            _fail("", f"missing key {key!r}")
    ver = cal["schema_version"]
    if not isinstance(ver, int) or isinstance(ver, bool):
        _fail("schema_version", f"must be an integer, got {_json_type(ver)}")
    if ver > SCHEMA_VERSION:
        _fail(
            "schema_version",
            f"{ver} is newer than this gridcal understands ({SCHEMA_VERSION}); upgrade gridcal",
        )
    if ver < 1:
        _fail("schema_version", f"must be >= 1, got {ver}")
    _object(cal["fingerprint"], "fingerprint")
    for where in ("meta", "fingerprint"):
        v = cal[where].get("cache_bytes") if isinstance(cal.get(where), dict) else None
        if v is not None and not (_is_number(v) and float(v).is_integer() and v > 0):
            _fail(f"{where}.cache_bytes", f"must be a whole number of bytes > 0, got {v!r}")
    _validate_fit(cal, "")
    _validate_constants(cal.get("isolated", {}), "isolated", partial=True)
    if "by_rays" in cal:
        for ray_set, entry in _object(cal["by_rays"], "by_rays").items():
            where = f"by_rays.{ray_set}"
            if not ray_set:
                _fail("by_rays", "a ray set's name must not be empty")
            entry = _object(entry, where)
            for key in BY_RAYS_KEYS:
                if key not in entry:
                    _fail(where, f"missing key {key!r}")
            for key in entry:
                if key not in BY_RAYS_KEYS:
                    _fail(where, f"unknown key {key!r} (known: {', '.join(BY_RAYS_KEYS)})")
            _validate_fit(entry, f"{where}.")
    meas = cal["measurements"]
    if not isinstance(meas, list):
        _fail("measurements", f"must be an array, got {_json_type(meas)}")
    for i, m in enumerate(meas):
        _validate_measurement(m, f"measurements[{i}]")
    _object(cal.get("meta", {}), "meta")
    if _has_t_mem(cal) or any(_has_t_mem(e) for e in (cal.get("by_rays") or {}).values()):
        if cache_bytes_of(cal) is None:
            _fail("meta.cache_bytes", "missing: the constants have T_mem, which needs the cache size it was "
                                      "measured against")
    return cal


# ---------------------------------------------------------------------------
# Reading and writing
# ---------------------------------------------------------------------------


def _reject_constant(name: str):
    raise UserError(f"contains {name}, which is not valid JSON; numbers must be finite")


def loads(text: str, source: str = "calibration") -> dict:
    """Parse and validate calibration JSON text; ``source`` prefixes messages."""
    try:
        obj = json.loads(text, parse_constant=_reject_constant)
    except UserError as exc:
        raise UserError(f"{source}: {exc}") from None
    except json.JSONDecodeError as exc:
        raise UserError(
            f"{source}: not valid JSON at line {exc.lineno} column {exc.colno} ({exc.msg}); "
            "the file may be truncated or corrupted"
        ) from None
    try:
        return validate(obj)
    except UserError as exc:
        raise UserError(f"{source}: {exc}") from None


def dumps(cal: Mapping) -> str:
    """Validate and serialise a calibration to JSON text (no NaN, UTF-8 safe)."""
    cal = _plain(cal)
    validate(cal)
    return json.dumps(cal, indent=1, allow_nan=False, ensure_ascii=False) + "\n"


def save(path, cal: Mapping) -> Path:
    """Validate ``cal`` and write it to ``path`` atomically; return the path."""
    return atomic_write_text(path, dumps(cal))


def load(path) -> dict:
    """Read and validate a calibration file.

    Raises UserError (a ValueError) naming the file and what is wrong: missing
    file, not UTF-8, invalid or truncated JSON, schema violations.
    """
    p = Path(path)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise UserError(f"{p}: no such calibration file; run `calibrate run` to create one") from None
    except IsADirectoryError:
        raise UserError(f"{p}: is a directory, not a calibration file") from None
    except OSError as exc:
        raise UserError(f"{p}: cannot read ({exc.strerror or exc})") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise UserError(f"{p}: not UTF-8 text (byte {exc.start}); not a calibration file") from None
    return loads(text, source=str(p))


def _plain(x):
    """Convert numpy scalars/arrays and tuples to plain JSON types."""
    if isinstance(x, Mapping):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return [_plain(v) for v in x.tolist()]
    if isinstance(x, np.bool_):
        return bool(x)
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.floating):
        return float(x)
    return x


# ---------------------------------------------------------------------------
# Building and re-fitting
# ---------------------------------------------------------------------------


def _stored_samples(result: _fit.FitResult) -> dict:
    values = np.column_stack([result.samples, result.tau_samples])
    n = values.shape[0]
    if n > MAX_STORED_SAMPLES:
        idx = np.round(np.linspace(0, n - 1, MAX_STORED_SAMPLES)).astype(int)
        values = values[idx]
    return {"columns": list(result.names) + [SCATTER_COLUMN], "values": values.tolist()}


def constants_json(result: _fit.FitResult) -> dict:
    """A fit's constants as the file stores them: name -> {median, ci68, ci95} or None.

    Also the form of ``isolated``: a fit of an isolating suite (``fit(...,
    required=("rays", "steps"))``) gives a partial block with None entries.
    """
    return {
        name: None if est is None else {"median": est["median"], "ci68": list(est["ci68"]), "ci95": list(est["ci95"])}
        for name, est in result.constants.items()
    }


def from_fit(
    result: _fit.FitResult,
    *,
    fingerprint: Mapping,
    measurements: list,
    isolated: Mapping | None = None,
    meta: Mapping | None = None,
    by_rays: Mapping[str, _fit.FitResult] | None = None,
) -> dict:
    """Assemble a calibration object from a fit and the raw measurements.

    result : FitResult of the in-context measurements.
    fingerprint : host facts (free-form JSON object).
    measurements : list of measurement records (see the module docstring).
    isolated : partial constants from isolating microbenchmarks ({} if none).
    by_rays : optional ray set -> FitResult of that ray set's in-context
        measurements alone (stored under ``by_rays``).
    Returns a validated, JSON-ready dict.
    """
    cal = {
        "schema_version": SCHEMA_VERSION,
        "fingerprint": dict(fingerprint),
        **_fit_block(result),
        "isolated": dict(isolated or {}),
        "measurements": list(measurements),
        "meta": dict(meta or {}),
    }
    if by_rays:
        cal["by_rays"] = {name: _fit_block(res) for name, res in by_rays.items()}
    cal = _plain(cal)
    return validate(cal)


def _fit_block(result: _fit.FitResult) -> dict:
    return {"constants": constants_json(result), "samples": _stored_samples(result),
            "diagnostics": dict(result.diagnostics)}


def fit_for_rays(cal: Mapping, rays: str | None) -> tuple[Mapping, str | None]:
    """The fit a prediction for ``rays`` should use: (object with ``constants``,
    ``samples`` and ``diagnostics``, the ray set it was fitted on or None).

    A calibration with a ``by_rays`` entry for ``rays`` gives that entry (the
    constants of that ray set alone); otherwise the fit of all in-context
    measurements, ``cal`` itself, with None.
    """
    entry = (cal.get("by_rays") or {}).get(rays) if rays else None
    return (entry, rays) if entry is not None else (cal, None)


def cache_bytes_of(cal: Mapping) -> int | None:
    """The cache size (bytes) a calibration's T_mem was measured against: ``meta.cache_bytes``,
    else ``fingerprint.cache_bytes``; None when the file records neither."""
    for where in ("meta", "fingerprint"):
        v = (cal.get(where) or {}).get("cache_bytes")
        if v is not None:
            return int(v)
    return None


def line_weights_of(cal: Mapping) -> dict | None:
    """The cache lines a step, an occupied cell entered and a test were charged when the
    calibration's T_mem was fitted (``meta.line_weights``, models.memory.line_weights); None
    when the file does not say (fitted before 2026-12-07: a line a step, 72/64 a test)."""
    w = (cal.get("meta") or {}).get("line_weights")
    return dict(w) if isinstance(w, Mapping) else None


def largest_grid_bytes(cal: Mapping) -> int | None:
    """Bytes of the largest grid a calibration timed in context (its memory term was
    fitted on grids up to this size); None when no in-context measurement records one."""
    sizes = [int(m.get("memory_bytes") or 0) for m in cal.get("measurements") or []
             if m.get("kind") == "in_context" and m.get("values_ns")]
    return max(sizes) if sizes and max(sizes) > 0 else None


def samples_by_name(cal: Mapping) -> dict[str, np.ndarray]:
    """Posterior samples of a (validated) calibration as name -> (S,) float arrays.

    Names are the stored columns (``t_setup_ns`` ... in ns, ``extra_scatter``
    in log units) plus ``ratio`` = T_int / T_step. ``cal`` may also be one
    entry of ``by_rays`` (see :func:`fit_for_rays`).
    """
    cols = cal["samples"]["columns"]
    values = np.asarray(cal["samples"]["values"], dtype=float).reshape(-1, len(cols))
    out = {name: values[:, k].copy() for k, name in enumerate(cols)}
    out[_fit.RATIO_NAME] = out["t_int_ns"] / out["t_step_ns"]
    return out


def apply_drift(measurements: list) -> list:
    """Divide the host's common slowdown out of every record that carries its raw values and stamps.

    Sets each such record's ``values_ns`` to ``raw_values_ns`` over the factors of
    :func:`calibrate.protocol.drift_factors`, estimated over all these records together
    (each value's neighbours in time are other configurations' values); records without
    stamps keep their values.  In place; returns ``measurements``.
    """
    from .protocol import drift_factors

    stamped = {i: m for i, m in enumerate(measurements) if m.get("stamps_s") and m.get("raw_values_ns")}
    if not stamped:
        return measurements
    factors = drift_factors({i: (m["raw_values_ns"], m["stamps_s"]) for i, m in stamped.items()})
    for i, m in stamped.items():
        m["values_ns"] = (np.asarray(m["raw_values_ns"], dtype=np.float64) / factors[i]).tolist()
    return measurements


def design_from_measurements(
    measurements: list,
    kind: str = "in_context",
    intersector: str | None = None,
    include_held_back: bool = False,
    optional: tuple = DEFAULT_OPTIONAL_COUNTS,
) -> dict:
    """Gather measurements of one kind into a design for :func:`calibrate.fit.fit`.

    measurements : validated measurement records.
    kind : "in_context" (the exported fit) or "isolated".
    intersector : keep only this intersector; when None all selected records
        must share one (records with intersector null are always kept).
    Records without values (an interrupted series) are skipped, and so are
    records marked ``held_back`` (kept out of the fit to test its predictions)
    unless ``include_held_back``.
    optional : the optional counts (of OPTIONAL_COUNT_FIELDS) to take, each when every
        chosen record has it; by default all (DEFAULT_OPTIONAL_COUNTS).
    Returns {rays, steps, tests, subgrids: (J,) float arrays, times_ns: J lists}, and
    ``misses`` (the memory effect's count), ``visits`` (occupied cells entered, plus the
    changes of occupancy when every chosen record carries ``changes``) and ``hits`` (rays
    that found a hit) as ``optional`` says.
    """
    if kind not in MEASUREMENT_KINDS:
        raise UserError(f"kind must be one of {', '.join(MEASUREMENT_KINDS)}, got {kind!r}")
    chosen = [m for m in measurements if m["kind"] == kind and m["values_ns"]
              and (include_held_back or not m.get("held_back", False))]
    if intersector is not None:
        chosen = [m for m in chosen if m["intersector"] in (None, intersector)]
    names = sorted({m["intersector"] for m in chosen if m["intersector"] is not None})
    if len(names) > 1:
        raise UserError(
            f"{kind} measurements mix intersectors ({', '.join(names)}), which have different T_int; "
            "choose one"
        )
    if not chosen:
        which = f" for intersector {intersector!r}" if intersector else ""
        raise UserError(f"no {kind} measurements with values{which}: nothing to fit")
    design = {k: np.array([float(m.get(k, 0)) for m in chosen]) for k in COUNT_FIELDS}
    for key in optional:
        if key not in OPTIONAL_COUNT_FIELDS:
            raise UserError(f"unknown optional count {key!r} (known: {', '.join(OPTIONAL_COUNT_FIELDS)})")
        if all(key in m for m in chosen):
            design[key] = np.array([float(m[key]) for m in chosen])
            if key == "visits" and all("changes" in m for m in chosen):
                # T_visit prices the changes of occupancy with the occupied cells entered: at
                # either the walk turns from stepping to testing or back
                # (models.general.occupancy_changes)
                design[key] = design[key] + np.array([float(m["changes"]) for m in chosen])
    design["times_ns"] = [list(map(float, m["values_ns"])) for m in chosen]
    return design


#: Least rise of the maximum log posterior for which an optional term (T_visit, T_mem, T_hit) is
#: fitted: half the 5% point of chi-square with one degree of freedom (3.84 / 2), a
#: likelihood-ratio test.
MEMORY_MIN_GAIN = 1.92
#: The optional terms, in the order they are tested: (count column, constant, what it is).
OPTIONAL_TERMS = (("visits", "t_visit_ns", "T_visit not fitted, occupied cells are priced as any cell step"),
                  ("misses", "t_mem_ns", "T_mem not fitted, the memory effect is left out"),
                  ("hits", "t_hit_ns", "T_hit not fitted, a ray that hits is priced as one that misses"))


def fit_in_context(design: Mapping, deadline: float | None = None, **fit_kwargs) -> _fit.FitResult:
    """:func:`calibrate.fit.fit` with the optional terms the timings call for.

    An optional term (T_visit when the design carries ``visits``, then T_mem when it
    carries ``misses``, then T_hit when it carries ``hits``) is fitted when adding it
    raises the maximum log posterior by at least MEMORY_MIN_GAIN (the timings reject
    T = 0 at the 5% level), given the terms already kept.  Otherwise, or when the fit
    with it fails (e.g. its interval reaches towards 0), the design is fitted without
    it, and ``diagnostics.t_visit_skipped``, ``t_mem_skipped`` or ``t_hit_skipped`` say
    why.  An error of the fit without them is raised as is.

    A fit with a term on trial checks every constant's interval after each chunk of its chain
    (``fail_fast``), not only the trial terms': with a term in, a required constant can be the one
    the timings cannot place.  Measured: the pooled fit of both ray sets with T_mem put T_step on
    a ridge down to 1e-6 ns, and the trials ran 10-19 thousand steps (10-13 s of a 60 s run, in
    every stage) before the same verdict; checked after each chunk, 2-4 s.

    ``deadline`` (``time.monotonic()``): a trial whose chain cannot converge by then ends, and
    its term is left out as for any failed trial; the fit without trial terms has no deadline,
    so there is always a result.
    """
    design = {k: v for k, v in design.items()
              if k not in OPTIONAL_COUNT_FIELDS or (v is not None and np.any(np.asarray(v) > 0))}
    short = {k: v for k, v in fit_kwargs.items() if k in ("seed", "required", "priors")}
    skipped = {}
    for col, name, label in OPTIONAL_TERMS:
        if col not in design:
            continue
        try:
            gain = _fit.log_posterior_gain(design, col, **short)
        except ValueError as exc:
            gain, why = -math.inf, str(exc)
        else:
            why = (f"adding it raises the maximum log posterior by {gain:.3g}, below {MEMORY_MIN_GAIN:g} "
                   f"(the timings do not reject {_fit.CONSTANT_LABELS[name]} = 0 at the 5% level)")
        if gain < MEMORY_MIN_GAIN:
            design = {k: v for k, v in design.items() if k != col}
            skipped[name] = f"{label}: {why}"
    while True:
        kept = tuple(name for col, name, _ in OPTIONAL_TERMS if col in design)
        try:
            result = (_fit.fit(design, fail_fast=_fit.CONSTANT_NAMES, deadline=deadline, **fit_kwargs) if kept
                      else _fit.fit(design, **fit_kwargs))
            break
        except (ValueError, _fit.ConvergenceError) as exc:
            if not kept:
                raise
            # the term the error names goes; when it names none, the last one tested
            named = [n for n in kept if _fit.CONSTANT_LABELS[n] in str(exc)]
            col, name, label = [t for t in OPTIONAL_TERMS if t[1] == (named or kept)[-1]][0]
            design = {k: v for k, v in design.items() if k != col}
            skipped[name] = f"{label}: {exc}"
    for name, why in skipped.items():
        result.diagnostics[f"{name[:-3]}_skipped"] = why
    return result


def stored_priors(cal: Mapping) -> dict:
    """The priors a calibration's pooled fit took from the isolating suites
    (``diagnostics.priors``), as ``{name: (median_ns, sigma_log)}``; UserError if malformed."""
    stored = cal["diagnostics"].get("priors") or {}
    try:
        return {str(k): (float(v[0]), float(v[1])) for k, v in stored.items()}
    except (TypeError, ValueError, IndexError):
        raise UserError("diagnostics.priors: must map constant names to [median_ns, sigma_log]") from None


def refit(cal: Mapping, *, seed: int = 0, intersector: str | None = None,
          optional: tuple = DEFAULT_OPTIONAL_COUNTS, **fit_kwargs) -> dict:
    """Re-fit the constants from a calibration's stored in-context measurements.

    Returns a new validated calibration: ``constants``, ``samples`` and
    ``diagnostics`` replaced, everything else kept.  The priors recorded in
    ``diagnostics.priors`` (from the isolating suites) are applied again. ``fit_kwargs`` go to
    :func:`calibrate.fit.fit` (e.g. ``max_steps``). Raises ValueError when the
    measurements cannot be fitted (see fit.fit).
    """
    cal = validate(_plain(cal))
    design = design_from_measurements(cal["measurements"], "in_context", intersector, optional=optional)
    if "priors" not in fit_kwargs:  # the priors the original fit took from the isolating suites
        fit_kwargs["priors"] = stored_priors(cal)
    result = fit_in_context(design, seed=seed, **fit_kwargs)
    by_rays, skipped = fit_by_rays(cal["measurements"], seed=seed, intersector=intersector, optional=optional,
                                   **fit_kwargs)
    meta = {k: v for k, v in cal.get("meta", {}).items() if k != "by_rays_skipped"}
    if skipped:
        meta["by_rays_skipped"] = skipped
    return from_fit(
        result,
        fingerprint=cal["fingerprint"],
        measurements=cal["measurements"],
        isolated=cal.get("isolated", {}),
        meta=meta,
        by_rays=by_rays,
    )


def ray_sets(measurements: list) -> list[str]:
    """The ray sets (``ray_set`` key) of in-context measurements, sorted; [] if unnamed."""
    return sorted({str(m["ray_set"]) for m in measurements
                   if m["kind"] == "in_context" and m.get("ray_set") and m["values_ns"]})


def fit_by_rays(measurements: list, *, seed: int = 0, intersector: str | None = None,
                optional: tuple = DEFAULT_OPTIONAL_COUNTS, **fit_kwargs) -> tuple[dict, dict]:
    """Fit each ray set's in-context measurements alone (when there are two or more sets).

    Rays of one set share a coherence: camera rays step in lockstep through
    neighbouring cells, isotropic ones do not, and a cell step of an incoherent
    ray costs 1.6 to 2.3 times as much (docs/calibration.md), so one set of
    constants for both fits neither well.
    Returns ({ray set: FitResult}, {ray set: why it was not fitted alone}).
    """
    fits, skipped = {}, {}
    names = ray_sets(measurements)
    if len(names) < 2:
        return fits, skipped
    for name in names:
        chosen = [m for m in measurements if m["kind"] == "in_context" and m.get("ray_set") == name]
        try:
            design = design_from_measurements(chosen, "in_context", intersector, optional=optional)
            fits[name] = fit_in_context(design, seed=seed, **fit_kwargs)
        except (ValueError, _fit.ConvergenceError) as exc:
            skipped[name] = str(exc)
    return fits, skipped
