"""Host fingerprint: complete, JSON-clean, and robust to a machine missing everything."""

import datetime as dt
import json
import os

import numpy as np
import pytest

from calibrate import host
from calibrate.host import FINGERPRINT_PACKAGES, fingerprint, package_versions

KEYS = {
    "cpu_model", "logical_cores", "affinity", "governor", "cpu_mhz", "os", "kernel",
    "platform", "machine", "python", "python_implementation", "packages", "timer",
    "timer_resolution_ns", "huge_pages", "date_utc",
}


def test_fingerprint_has_the_keys_and_is_json():
    fp = fingerprint()
    assert KEYS <= set(fp)
    assert "hostname" not in fp and "node" not in fp
    assert json.loads(json.dumps(fp)) == fp
    assert set(fp["packages"]) == set(FINGERPRINT_PACKAGES)
    assert fp["packages"]["numpy"] == np.__version__
    assert fp["logical_cores"] == os.cpu_count()
    assert fp["timer_resolution_ns"] >= 1.0
    when = dt.datetime.fromisoformat(fp["date_utc"])
    assert when.utcoffset() == dt.timedelta(0)
    assert abs((dt.datetime.now(dt.timezone.utc) - when).total_seconds()) < 60


def test_extra_is_merged_and_checked():
    fp = fingerprint({"compiler": "cc 12.2", "cflags": ["-O2", "-march=native"]})
    assert fp["compiler"] == "cc 12.2" and fp["cflags"] == ["-O2", "-march=native"]
    with pytest.raises(ValueError, match="collide"):
        fingerprint({"cpu_model": "mine"})
    with pytest.raises(ValueError, match="JSON"):
        fingerprint({"compiler": object()})


def test_planted_linux_files_are_read(tmp_path, monkeypatch):
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text("processor\t: 0\nvendor_id\t: Planted\n"
                       "model name\t: Planted CPU 9000 @ 3.20GHz\ncpu MHz\t\t: 1234.5\n")
    freq = tmp_path / "cpufreq"
    freq.mkdir()
    (freq / "scaling_governor").write_text("performance\n")
    (freq / "scaling_cur_freq").write_text("3200000\n")  # kHz
    monkeypatch.setattr(host, "CPUINFO_PATH", cpuinfo)
    monkeypatch.setattr(host, "CPUFREQ_DIR", freq)
    thp = tmp_path / "thp"
    thp.write_text("always [madvise] never\n")
    monkeypatch.setattr(host, "THP_PATH", thp)
    fp = fingerprint()
    assert fp["huge_pages"] == "madvise"
    assert fp["cpu_model"] == "Planted CPU 9000 @ 3.20GHz"
    assert fp["governor"] == "performance"
    assert fp["cpu_mhz"] == 3200.0  # cpufreq preferred over cpuinfo
    (freq / "scaling_cur_freq").unlink()
    assert fingerprint()["cpu_mhz"] == 1234.5  # cpuinfo fallback


def test_missing_everything_gives_nulls_not_errors(tmp_path, monkeypatch):
    monkeypatch.setattr(host, "CPUINFO_PATH", tmp_path / "absent" / "cpuinfo")
    monkeypatch.setattr(host, "CPUFREQ_DIR", tmp_path / "absent")
    monkeypatch.setattr(host, "THP_PATH", tmp_path / "absent" / "enabled")
    monkeypatch.delattr(os, "sched_getaffinity", raising=False)
    monkeypatch.setattr(os, "cpu_count", lambda: None)
    fp = fingerprint()
    assert fp["governor"] is None and fp["cpu_mhz"] is None and fp["affinity"] is None
    assert fp["huge_pages"] is None
    assert fp["logical_cores"] is None
    assert fp["cpu_model"] is None or isinstance(fp["cpu_model"], str)  # platform fallback
    json.dumps(fp)


def test_garbage_files_give_nulls(tmp_path, monkeypatch):
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_bytes(b"\xff\xfe no colon here\ncpu MHz : fast\n")
    freq = tmp_path / "cpufreq"
    freq.mkdir()
    (freq / "scaling_governor").write_text("\n")
    (freq / "scaling_cur_freq").write_text("n/a\n")
    monkeypatch.setattr(host, "CPUINFO_PATH", cpuinfo)
    monkeypatch.setattr(host, "CPUFREQ_DIR", freq)
    thp = tmp_path / "thp"
    thp.write_text("always madvise never []\n")  # no mode selected
    monkeypatch.setattr(host, "THP_PATH", thp)
    fp = fingerprint()
    assert fp["governor"] is None and fp["cpu_mhz"] is None and fp["huge_pages"] is None
    json.dumps(fp)


def test_package_versions_missing_is_null():
    v = package_versions(("numpy", "no-such-distribution-gridcal"))
    assert v == {"numpy": np.__version__, "no-such-distribution-gridcal": None}
