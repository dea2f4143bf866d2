"""Host fingerprint recorded with every calibration.

pyperf stores CPU model, frequency, affinity and timer resolution with each
result; this module gathers the same facts. Every probe is defensive: a missing
file, an unreadable sysfs entry or an absent package yields ``None``, never an
exception, and the result is plain JSON (str, int, float, bool, None, list, dict).
The hostname is deliberately not recorded.
"""

from __future__ import annotations

import datetime as _dt
import importlib.metadata
import json
import os
import platform
from pathlib import Path

from .protocol import timer_info

__all__ = ["FINGERPRINT_PACKAGES", "cache_bytes", "fingerprint", "package_versions"]

# Packages whose versions affect results or their fits.
FINGERPRINT_PACKAGES = ("numpy", "nlopt", "emcee", "jax", "trimesh")
# Linux sources (module-level so tests can point them at missing files).
CPUINFO_PATH = Path("/proc/cpuinfo")
CPUFREQ_DIR = Path("/sys/devices/system/cpu/cpu0/cpufreq")
KHZ_PER_MHZ = 1000.0
CACHE_DIR = Path("/sys/devices/system/cpu/cpu0/cache")
#: Transparent huge pages: the kernels ask for them on a grid's arrays of 2 MiB and more
#: (kernels/bigmem.c), which the OS grants in mode "always" or "madvise".
THP_PATH = Path("/sys/kernel/mm/transparent_hugepage/enabled")
#: The smallest cache size ``calibrate run`` tries for the memory effect's C (models/memory.py):
#: the per-core level-2 cache, which a traversal's cells and triangles spill out of first.
CACHE_LEVEL = 2
#: The last-level cache: the largest size ``calibrate run`` tries for the memory effect's C.
LAST_CACHE_LEVEL = 3
#: Assumed when the operating system does not say (1 MiB: the smallest per-core
#: level-2 cache of current x86-64 and arm64 server cores); stored as assumed.
DEFAULT_CACHE_BYTES = 1 << 20
_SIZE_UNITS = {"": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30}


def _read_text(path: Path) -> str | None:
    """File contents, or None if it cannot be read for any reason."""
    try:
        return Path(path).read_text(encoding="utf-8", errors="replace")
    except (OSError, ValueError):
        return None


def _cpuinfo_field(text: str | None, key: str) -> str | None:
    """First value of ``key`` in /proc/cpuinfo-style ``key : value`` text."""
    if not text:
        return None
    for line in text.splitlines():
        k, sep, v = line.partition(":")
        if sep and k.strip() == key:
            return v.strip() or None
    return None


def _to_float(s: str | None) -> float | None:
    try:
        return float(s) if s is not None else None
    except ValueError:
        return None


def _cpu_model(cpuinfo: str | None) -> str | None:
    model = _cpuinfo_field(cpuinfo, "model name")  # x86
    if model is None:
        model = _cpuinfo_field(cpuinfo, "Model")  # some ARM boards
    if model is None:
        model = platform.processor() or platform.machine() or None
    return model


def _cpu_mhz(cpuinfo: str | None) -> float | None:
    """Current frequency of CPU 0 in MHz (cpufreq first, then /proc/cpuinfo)."""
    khz = _to_float((_read_text(CPUFREQ_DIR / "scaling_cur_freq") or "").strip() or None)
    if khz is not None:
        return khz / KHZ_PER_MHZ
    return _to_float(_cpuinfo_field(cpuinfo, "cpu MHz"))


def _huge_pages(text: str | None) -> str | None:
    """The selected mode of "always [madvise] never" (the bracketed word), or None."""
    for word in (text or "").split():
        if len(word) > 2 and word[0] == "[" and word[-1] == "]":
            return word[1:-1]
    return None


def _affinity() -> list[int] | None:
    try:
        return sorted(int(c) for c in os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return None


def package_versions(names=FINGERPRINT_PACKAGES) -> dict[str, str | None]:
    """Installed version of each distribution name, None when missing."""
    out: dict[str, str | None] = {}
    for name in names:
        try:
            out[name] = importlib.metadata.version(name)
        except Exception:  # PackageNotFoundError or a broken metadata dir
            out[name] = None
    return out


def _safe(probe, default=None):
    try:
        return probe()
    except Exception:
        return default


def _parse_size(text: str | None) -> int | None:
    """sysfs cache size ("2048K", "1M", "512") -> bytes, or None."""
    if text is None:
        return None
    t = text.strip().upper()
    unit = t[-1:] if t[-1:] in ("K", "M", "G") else ""
    digits = t[:-1] if unit else t
    if not digits.isdigit() or int(digits) <= 0:
        return None
    return int(digits) * _SIZE_UNITS[unit]


def cache_bytes(level: int = CACHE_LEVEL, cache_dir: Path | None = None) -> tuple[int, str]:
    """(bytes, source) of CPU 0's data or unified cache at ``level``.

    source is the sysfs file read, or "assumed" with DEFAULT_CACHE_BYTES when the
    operating system does not say (not Linux, or no such level).
    """
    base = CACHE_DIR if cache_dir is None else Path(cache_dir)
    try:
        entries = sorted(base.glob("index*"))
    except OSError:
        entries = []
    for entry in entries:
        lvl = _read_text(entry / "level")
        kind = _read_text(entry / "type")
        if lvl is None or kind is None or lvl.strip() != str(level) or kind.strip() not in ("Data", "Unified"):
            continue
        size = _parse_size(_read_text(entry / "size"))
        if size is not None:
            return size, str(entry / "size")
    return DEFAULT_CACHE_BYTES, "assumed"


def last_cache_bytes(cache_dir: Path | None = None) -> int | None:
    """Bytes of CPU 0's level-3 (last-level) data or unified cache, or None when the OS does not say."""
    size, source = cache_bytes(LAST_CACHE_LEVEL, cache_dir)
    return None if source == "assumed" else size


def fingerprint(extra: dict | None = None) -> dict:
    """Facts about this host that a calibration depends on.

    extra : optional JSON-serialisable dict merged at top level (e.g. the
        kernels' compiler and flags); a key that collides with a built-in key
        raises ValueError.
    Returns a JSON-serialisable dict with keys: cpu_model, logical_cores,
    affinity (list of CPU indices or None), governor, cpu_mhz, os, kernel,
    platform, machine, python, python_implementation, packages (name ->
    version or None), timer (see ``protocol.timer_info``),
    timer_resolution_ns, cache_bytes and cache_source (see :func:`cache_bytes`),
    huge_pages (the transparent huge page mode: "always", "madvise", "never"),
    date_utc (ISO 8601). Missing facts are None.
    """
    cpuinfo = _read_text(CPUINFO_PATH)
    governor = _read_text(CPUFREQ_DIR / "scaling_governor")
    timer = _safe(timer_info, {})
    cache, cache_source = _safe(cache_bytes, (DEFAULT_CACHE_BYTES, "assumed"))
    fp = {
        "cpu_model": _safe(lambda: _cpu_model(cpuinfo)),
        "logical_cores": _safe(os.cpu_count),
        "affinity": _affinity(),
        "governor": (governor.strip() or None) if governor is not None else None,
        "cpu_mhz": _safe(lambda: _cpu_mhz(cpuinfo)),
        "os": _safe(platform.system) or None,
        "kernel": _safe(platform.release) or None,
        "platform": _safe(platform.platform) or None,
        "machine": _safe(platform.machine) or None,
        "python": platform.python_version(),
        "python_implementation": platform.python_implementation(),
        "packages": package_versions(),
        "timer": timer,
        "timer_resolution_ns": timer.get("resolution_ns"),
        "cache_bytes": cache,
        "cache_source": cache_source,
        "huge_pages": _safe(lambda: _huge_pages(_read_text(THP_PATH))),
        "date_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    }
    if extra:
        clash = sorted(set(extra) & set(fp))
        if clash:
            raise ValueError(f"fingerprint: extra keys collide with built-in keys {clash}")
        try:
            json.dumps(extra)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"fingerprint: extra is not JSON-serialisable ({exc})") from exc
        fp.update(extra)
    return fp
