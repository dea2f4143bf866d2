"""Tests of calibrate.calfile (schema, validation, re-fit) and calibrate._io (atomic writes)."""

from __future__ import annotations

import copy
import json
import os
import stat
import tempfile
from pathlib import Path

import numpy as np
import pytest

from calibrate import _io, calfile
from calibrate import fit as F

TRUE_NS = {"t_setup_ns": 40.0, "t_step_ns": 3.0, "t_int_ns": 7.5, "t_sub_ns": 15.0}
RAYS_PER_BATCH = 4096
NOISE_REL = 0.05
N_IN_CONTEXT = 24
N_ISOLATED = 6
N_REPEATS = 5


def synthetic_measurements(rng: np.random.Generator) -> list[dict]:
    """Measurement records as `calibrate run` stores them, with planted constants.

    In-context: scenes x resolutions, some nested (subgrids > 0); isolated:
    empty grids of growing m (no intersector). values_ns are ns per batch.
    """
    records = []
    for j in range(N_IN_CONTEXT + N_ISOLATED):
        isolated = j >= N_IN_CONTEXT
        m = int(rng.integers(2, 200))
        steps_pr = m * rng.uniform(0.5, 1.5) if isolated else np.exp(rng.uniform(np.log(10), np.log(2000)))
        tests_pr = 0.0 if isolated else np.exp(rng.uniform(0.0, np.log(500)))
        sub_pr = rng.uniform(5, 50) if (not isolated and j % 3 == 0) else 0.0
        counts = {k: int(round(RAYS_PER_BATCH * v)) for k, v in (("steps", steps_pr), ("tests", tests_pr), ("subgrids", sub_pr))}
        mu = (
            RAYS_PER_BATCH * TRUE_NS["t_setup_ns"]
            + counts["steps"] * TRUE_NS["t_step_ns"]
            + counts["tests"] * TRUE_NS["t_int_ns"]
            + counts["subgrids"] * TRUE_NS["t_sub_ns"]
        )
        values = mu * np.exp(NOISE_REL * rng.standard_normal(N_REPEATS))
        records.append(
            {
                "kind": "isolated" if isolated else "in_context",
                "scene": "empty" if isolated else ("bunny", "cube", "sponza")[j % 3],
                "resolution": [m, m, m] if j % 3 else [[m, m, m], [4, 4, 4]],
                "intersector": None if isolated else "moller",
                "rays": RAYS_PER_BATCH,
                **counts,
                "values_ns": [float(v) for v in values],
                "loops": 3,  # extra keys from the protocol are kept
            }
        )
    return records


@pytest.fixture(scope="module")
def good_cal() -> dict:
    measurements = synthetic_measurements(np.random.default_rng(42))
    design = calfile.design_from_measurements(measurements)
    result = F.fit(design, seed=0)
    return calfile.from_fit(
        result,
        fingerprint={"cpu_model": "Test CPU @ 3.0GHz", "logical_cores": 2},
        measurements=measurements,
        isolated={"t_step_ns": {"median": 2.9, "ci95": [2.7, 3.1]}},
        meta={"budget_s": 60},
    )


def write(tmp_path: Path, obj_or_text, name="calibration.json") -> Path:
    path = tmp_path / name
    if isinstance(obj_or_text, (bytes, str)):
        data = obj_or_text if isinstance(obj_or_text, bytes) else obj_or_text.encode()
    else:
        data = json.dumps(obj_or_text).encode()
    path.write_bytes(data)
    return path


# --- round trip and re-fit -------------------------------------------------------


def test_round_trip(tmp_path, good_cal):
    path = calfile.save(tmp_path / "calibration.json", good_cal)
    loaded = calfile.load(path)
    assert loaded == good_cal
    c = loaded["constants"]
    for name in ("t_setup_ns", "t_step_ns", "t_int_ns", "t_sub_ns", "ratio"):
        assert set(c[name]) == {"median", "ci68", "ci95"}
    assert c["ratio"]["ci95"][0] < TRUE_NS["t_int_ns"] / TRUE_NS["t_step_ns"] < c["ratio"]["ci95"][1]
    assert loaded["samples"]["columns"] == ["t_setup_ns", "t_step_ns", "t_int_ns", "t_sub_ns", "extra_scatter"]
    assert len(loaded["measurements"]) == N_IN_CONTEXT + N_ISOLATED
    assert loaded["measurements"][0]["loops"] == 3
    samples = calfile.samples_by_name(loaded)
    assert samples["ratio"].shape == (len(loaded["samples"]["values"]),)
    assert np.median(samples["t_step_ns"]) == pytest.approx(c["t_step_ns"]["median"], rel=0.01)
    # Saving what was loaded gives the same bytes.
    assert calfile.dumps(loaded) == path.read_text()


def test_refit_from_stored_measurements_reproduces_the_fit(good_cal):
    again = calfile.refit(good_cal, seed=0)
    assert again["constants"] == good_cal["constants"]
    assert again["samples"] == good_cal["samples"]
    assert again["measurements"] == good_cal["measurements"]
    assert again["isolated"] == good_cal["isolated"]


def test_uniform_only_calibration_has_null_t_sub(tmp_path, good_cal):
    measurements = copy.deepcopy([m for m in good_cal["measurements"] if m["subgrids"] == 0])
    for m in measurements[::2]:
        del m["subgrids"]  # an absent count means 0
    cal = dict(good_cal, measurements=measurements)
    cal = calfile.refit(cal, seed=1, autocorr_tol=25.0)
    assert cal["constants"]["t_sub_ns"] is None
    assert "t_sub_ns" not in cal["samples"]["columns"]
    assert calfile.load(calfile.save(tmp_path / "u.json", cal)) == cal
    # A file that omits t_sub_ns altogether is read too.
    del cal["constants"]["t_sub_ns"]
    calfile.validate(cal)


def test_isolated_block_from_a_partial_fit(good_cal):
    design = calfile.design_from_measurements(good_cal["measurements"], kind="isolated")
    iso = calfile.constants_json(F.fit(design, seed=0, required=("rays", "steps"), autocorr_tol=25.0))
    assert iso["t_int_ns"] is None and iso["ratio"] is None
    assert iso["t_step_ns"]["ci95"][0] < TRUE_NS["t_step_ns"] < iso["t_step_ns"]["ci95"][1]
    calfile.validate(dict(good_cal, isolated=iso))


def test_design_selection(good_cal):
    ms = copy.deepcopy(good_cal["measurements"])
    ms[0]["values_ns"] = []  # an interrupted series is skipped
    d = calfile.design_from_measurements(ms)
    assert len(d["times_ns"]) == N_IN_CONTEXT - 1
    iso = calfile.design_from_measurements(ms, kind="isolated")
    assert len(iso["rays"]) == N_ISOLATED and not np.any(iso["tests"])
    ms[1]["intersector"] = "watertight"
    with pytest.raises(ValueError, match=r"mix intersectors \(moller, watertight\)"):
        calfile.design_from_measurements(ms)
    assert len(calfile.design_from_measurements(ms, intersector="watertight")["rays"]) == 1
    with pytest.raises(ValueError, match="no in_context measurements"):
        calfile.design_from_measurements(ms, intersector="embree")


# --- bad files -------------------------------------------------------------------


def _set(path: str, value):
    def mutate(cal):
        keys = path.split(".")
        obj = cal
        for k in keys[:-1]:
            obj = obj[int(k)] if isinstance(obj, list) else obj[k]
        last = keys[-1]
        if value is _DELETE:
            del obj[last]
        elif isinstance(obj, list):
            obj[int(last)] = value
        else:
            obj[last] = value
        return cal

    return mutate


_DELETE = object()

BAD_OBJECTS = [
    ("missing top key", _set("constants", _DELETE), r"missing key 'constants'"),
    ("missing constant", _set("constants.t_int_ns", _DELETE), r"constants: missing key 't_int_ns'"),
    ("wrong type", _set("constants.t_step_ns.median", "3.0"), r"constants\.t_step_ns\.median: must be a number, got str"),
    ("negative constant", _set("constants.t_step_ns.median", -3.0), r"constants\.t_step_ns\.median: must be positive"),
    ("ci misses median", _set("constants.t_int_ns.ci95", [1.0, 2.0]), r"constants\.t_int_ns\.ci95: interval \[1, 2\] does not contain the median"),
    ("ci reversed", _set("constants.ratio.ci68", [3.0, 2.0]), r"constants\.ratio\.ci68: low 3 is above high 2"),
    ("future schema", _set("schema_version", 2), r"schema_version: 2 is newer than this gridcal understands \(1\)"),
    ("schema not int", _set("schema_version", "1"), r"schema_version: must be an integer, got string"),
    ("unknown constant", _set("constants.t_stp_ns", {"median": 1.0}), r"unknown constant 't_stp_ns'"),
    ("samples shape", _set("samples.values.3", [1.0, 2.0]), r"samples\.values: shape mismatch: row 3 has 2 values but there are 5 columns"),
    ("sample not positive", _set("samples.values.0.1", 0.0), r"samples\.values\[0\]\[1\]: t_step_ns must be positive"),
    ("negative count", _set("measurements.4.tests", -1), r"measurements\[4\]\.tests: negative count -1"),
    ("fractional count", _set("measurements.4.steps", 10.5), r"measurements\[4\]\.steps: count must be a whole number"),
    ("bad kind", _set("measurements.2.kind", "in-situ"), r"measurements\[2\]\.kind: must be one of isolated, in_context"),
    ("negative time", _set("measurements.1.values_ns.0", -5.0), r"measurements\[1\]\.values_ns\[0\]: negative time"),
    ("measurement not object", _set("measurements.0", [1, 2]), r"measurements\[0\]: must be a JSON object, got array"),
    ("bad resolution", _set("measurements.1.resolution", [0, 4, 4]), r"measurements\[1\]\.resolution\[0\]: must be a positive integer"),
    ("not converged", _set("diagnostics.converged", False), r"diagnostics\.converged: is not true"),
    ("fingerprint not object", _set("fingerprint", "x86"), r"fingerprint: must be a JSON object, got string"),
    ("raw values without stamps", _set("measurements.1.raw_values_ns", [1.0] * 5),
     r"measurements\[1\]: raw_values_ns and stamps_s come together"),
    ("stamps for fewer values", lambda c: _set("measurements.1.stamps_s", [1.0, 2.0])(
        _set("measurements.1.raw_values_ns", [1.0] * 5)(c)), r"measurements\[1\]\.stamps_s: has 2 entries for 5 values"),
    ("raw value not positive", lambda c: _set("measurements.1.stamps_s", [1.0] * 5)(
        _set("measurements.1.raw_values_ns", [0.0] * 5)(c)), r"measurements\[1\]\.raw_values_ns\[0\]: time must be positive"),
]


@pytest.mark.parametrize("label, mutate, message", BAD_OBJECTS, ids=[b[0] for b in BAD_OBJECTS])
def test_bad_calibration_objects_rejected(tmp_path, good_cal, label, mutate, message):
    path = write(tmp_path, mutate(copy.deepcopy(good_cal)))
    with pytest.raises(ValueError, match=message) as info:
        calfile.load(path)
    assert str(info.value).startswith(str(path))  # the message names the file
    assert isinstance(info.value, _io.UserError)


def _nan_median(text: str) -> str:
    obj = json.loads(text)
    med = obj["constants"]["t_step_ns"]["median"]
    return text.replace(f'"median": {json.dumps(med)}', '"median": NaN', 1)


BAD_TEXTS = [
    ("truncated", lambda t: t[: len(t) // 2], r"not valid JSON at line \d+ column \d+ .*truncated"),
    ("empty", lambda t: "", r"not valid JSON at line 1 column 1"),
    ("NaN constant", _nan_median, r"contains NaN, which is not valid JSON"),
    ("not an object", lambda t: "[1, 2, 3]", r"a calibration must be a JSON object, got array"),
    ("not utf-8", lambda t: b"\xff\xfe\x00garbage", r"not UTF-8 text"),
]


@pytest.mark.parametrize("label, corrupt, message", BAD_TEXTS, ids=[b[0] for b in BAD_TEXTS])
def test_bad_calibration_texts_rejected(tmp_path, good_cal, label, corrupt, message):
    text = calfile.dumps(good_cal)
    if label == "NaN constant":
        assert "NaN" in corrupt(text)
    path = write(tmp_path, corrupt(text))
    with pytest.raises(ValueError, match=message):
        calfile.load(path)


def test_missing_file_and_directory_rejected(tmp_path):
    with pytest.raises(ValueError, match="no such calibration file; run `calibrate run`"):
        calfile.load(tmp_path / "absent.json")
    with pytest.raises(ValueError, match="is a directory"):
        calfile.load(tmp_path)


def test_save_validates_before_writing(tmp_path, good_cal):
    path = calfile.save(tmp_path / "calibration.json", good_cal)
    before = path.read_bytes()
    bad = copy.deepcopy(good_cal)
    bad["constants"]["t_step_ns"]["median"] = float("nan")
    with pytest.raises(ValueError, match=r"constants\.t_step_ns\.median: must be finite"):
        calfile.save(path, bad)
    assert path.read_bytes() == before


# --- atomic writes -----------------------------------------------------------------


def _leftovers(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir() if p.name.endswith(".tmp"))


def test_atomic_write_replaces_and_keeps_mode(tmp_path):
    path = tmp_path / "out.txt"
    _io.atomic_write_text(path, "first\n")
    assert path.read_text() == "first\n"
    os.chmod(path, 0o640)
    _io.atomic_write_text(path, "second\n")
    assert path.read_text() == "second\n"
    assert stat.S_IMODE(path.stat().st_mode) == 0o640
    _io.atomic_write_bytes(tmp_path / "new.bin", b"\x00\x01")
    mask = os.umask(0)
    os.umask(mask)
    assert stat.S_IMODE((tmp_path / "new.bin").stat().st_mode) == 0o666 & ~mask
    assert _leftovers(tmp_path) == []


@pytest.mark.parametrize("failing", ["fsync", "replace", "write"])
def test_failed_write_leaves_existing_file_intact(tmp_path, monkeypatch, failing):
    path = tmp_path / "calibration.json"
    path.write_text("old content\n")

    def boom(*args, **kwargs):
        raise OSError(28, "No space left on device")

    if failing == "write":
        real_fdopen = os.fdopen

        class FullDisk:
            def __init__(self, fh):
                self.fh = fh

            def __enter__(self):
                return self

            def __exit__(self, *exc):
                self.fh.close()

            def write(self, data):
                self.fh.write(data[:3])  # a partial write, then the disk is full
                boom()

            def __getattr__(self, name):
                return getattr(self.fh, name)

        monkeypatch.setattr(os, "fdopen", lambda fd, mode: FullDisk(real_fdopen(fd, mode)))
    else:
        monkeypatch.setattr(os, failing, boom)
    with pytest.raises(_io.UserError, match=r"cannot write .*calibration\.json: disk full; the existing file is unchanged"):
        _io.atomic_write_text(path, "new content that must not appear\n")
    monkeypatch.undo()
    assert path.read_text() == "old content\n"
    assert _leftovers(tmp_path) == []


def test_interrupt_during_write_leaves_existing_file_intact(tmp_path, monkeypatch):
    path = tmp_path / "calibration.json"
    path.write_text("old\n")

    def interrupt(*args):
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "fsync", interrupt)
    with pytest.raises(KeyboardInterrupt):
        _io.atomic_write_text(path, "new\n")
    monkeypatch.undo()
    assert path.read_text() == "old\n"
    assert _leftovers(tmp_path) == []


def test_output_path_mistakes_give_clear_messages(tmp_path, monkeypatch):
    with pytest.raises(ValueError, match="is a directory; give a file name"):
        _io.atomic_write_text(tmp_path, "x")
    with pytest.raises(ValueError, match=r"directory .*missing does not exist"):
        _io.atomic_write_text(tmp_path / "missing" / "out.json", "x")

    def denied(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    # Simulated, so the case is covered even when tests run as root.
    monkeypatch.setattr(tempfile, "mkstemp", denied)
    with pytest.raises(ValueError, match="is not writable"):
        _io.atomic_write_text(tmp_path / "out.json", "x")


@pytest.mark.skipif(
    not hasattr(os, "geteuid") or os.geteuid() == 0,
    reason="root ignores directory permissions, so a read-only directory cannot be tested",
)
def test_read_only_directory(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    (ro / "calibration.json").write_text("old\n")
    os.chmod(ro, 0o555)
    try:
        with pytest.raises(ValueError, match="is not writable"):
            _io.atomic_write_text(ro / "calibration.json", "new\n")
        assert (ro / "calibration.json").read_text() == "old\n"
    finally:
        os.chmod(ro, 0o755)


def test_apply_drift_divides_the_common_slowdown_out_of_stamped_records(good_cal):
    """Records with raw values and stamps get values_ns = raw / the neighbours' slowdown
    (recomputed from the raw values whatever values_ns held); records without keep theirs."""
    recs = copy.deepcopy(good_cal["measurements"])
    rng = np.random.default_rng(7)
    order = rng.permutation([(j, k) for j in range(len(recs) - 1) for k in range(N_REPEATS)])
    slow = np.exp(0.3 * np.sin(np.arange(len(order)) / 6.0))  # a slowdown lasting many values
    stamps = {j: [0.0] * N_REPEATS for j in range(len(recs) - 1)}
    raw = {j: [0.0] * N_REPEATS for j in range(len(recs) - 1)}
    for t, (j, k) in enumerate(order):
        stamps[j][k] = 0.01 * t
        raw[j][k] = recs[j]["values_ns"][k] * slow[t]
    for j in stamps:
        recs[j].update(raw_values_ns=raw[j], stamps_s=stamps[j], values_ns=[1.0] * N_REPEATS)
    untouched = list(recs[-1]["values_ns"])
    calfile.apply_drift(recs)
    assert recs[-1]["values_ns"] == untouched and "raw_values_ns" not in recs[-1]
    spread = lambda v: float(np.median(np.abs(np.log(v) - np.median(np.log(v)))))
    before = np.median([spread(raw[j]) for j in raw])
    after = np.median([spread(recs[j]["values_ns"]) for j in raw])
    assert before > 0.1 and after < 0.5 * before
    calfile.validate(dict(good_cal, measurements=recs))  # what apply_drift leaves is a valid file
