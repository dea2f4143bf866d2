"""Scene and Grid: the Python face of the C kernels.

A :class:`Scene` is a validated triangle mesh (``vertices (V, 3) float64``,
``faces (F, 3) int64``) with its grid box.  A :class:`Grid` is a built uniform
or nested grid over a scene; it traces rays with the timed twin
(:meth:`Grid.intersect`, :meth:`Grid.bench`) and counts work with the
instrumented twin (:meth:`Grid.count`).  Every bad input raises ``ValueError``
with a message naming the problem.
"""

from __future__ import annotations

import math
import numbers
import os
import reprlib
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from models.stats import grid_box

from . import _kernels

#: Intersector names accepted wherever one is chosen.
INTERSECTORS = {
    "watertight": _kernels.WATERTIGHT,
    "moller-trumbore": _kernels.MOLLER_TRUMBORE,
}
_INTERSECTOR_ALIASES = {"wt": "watertight", "mt": "moller-trumbore", "moller_trumbore": "moller-trumbore"}
INSERTIONS = {"exact": _kernels.INSERT_EXACT, "bounds": _kernels.INSERT_BOUNDS}
#: Manta RecursiveGrid's per-level constant: total cells = (8 n)^(3 / (2L + 1 - 2 depth)).
MANTA_SCALE = 8.0
#: Clocks :meth:`Grid.timed_batch` can time with: the kernel's monotonic clock, or the thread's CPU time.
TIMING_CLOCKS = ("wall", "thread")
#: Cells holding at most this many references keep their list instead of a subgrid.
DEFAULT_SUBDIVIDE_THRESHOLD = 2
#: Largest per-axis resolution the nesting rule gives a subgrid.
DEFAULT_RULE_MAX_AXIS = 256
#: Threads a build uses by default: its passes over the triangles and the references run in
#: two parts at once (the grid is the same, byte for byte, for any number).
DEFAULT_BUILD_THREADS = 2
#: Levels a nested grid may have (top level included).
MAX_LEVELS = _kernels.MAX_LEVELS
#: Most threads a build uses (the kernel's GC_MAX_THREADS).
MAX_BUILD_THREADS = _kernels.MAX_BUILD_THREADS
#: Largest subdivide threshold (references per cell): a cell subdivides when its uint32_t
#: reference count exceeds the threshold, and 2^32 - 2 is the largest such a count can exceed.
MAX_SUBDIVIDE_THRESHOLD = 2**32 - 2
#: Largest per-axis cell count: the kernel holds resolutions in an int32_t.
MAX_AXIS_CELLS = 2**31 - 1
#: Largest memory limit (bytes) and loop count: both must fit a signed 64-bit integer.
MAX_INT64 = 2**63 - 1
#: Rays a primed value traces, untimed, before it (``prime`` of :meth:`Grid.timed_batch`'s callable,
#: which :func:`calibrate.protocol.measure` calls): the first of its batch.  They warm what a
#: stream of such rays keeps cached (the grid's cells near the box, the triangles rays meet
#: most) without tracing a long batch twice for every value.
PRIME_RAYS = 2048
#: Resolution axes up to this many cells print in full in messages; larger ones as 3 significant digits.
MAX_PRINTED_AXIS_DIGITS = 12

_SHORT_REPR = reprlib.Repr()
_SHORT_REPR.maxlong = 24
_SHORT_REPR.maxstring = 40
_SHORT_REPR.maxother = 60


def _show(value) -> str:
    """A short repr of a user's value for an error message (long numbers, strings, lists cut)."""
    return _SHORT_REPR.repr(value)


def _is_bool(value) -> bool:
    return isinstance(value, (bool, np.bool_))


def _is_real(value) -> bool:
    """A real number (Python or numpy), not a bool and not a string."""
    return isinstance(value, numbers.Real) and not _is_bool(value)


def _whole_number(value, name: str, lo: int, hi: int, hi_text: str) -> int:
    """``value`` as an int when it is a whole number (int or numpy integer, not bool) in [lo, hi]."""
    if not (isinstance(value, numbers.Integral) and not _is_bool(value) and lo <= int(value) <= hi):
        raise ValueError(f"{name} must be a whole number from {lo} to {hi_text}, got {_show(value)}")
    return int(value)


def _flag(value, name: str) -> bool:
    """``value`` as a bool when it is True or False (Python or numpy)."""
    if not _is_bool(value):
        raise ValueError(f"{name} must be True or False, got {_show(value)}")
    return bool(value)


def _as_array(value, name: str, shape: str) -> np.ndarray:
    """np.asarray(value); a ragged or unconvertible sequence raises ValueError naming ``name``."""
    try:
        return np.asarray(value)
    except (ValueError, TypeError) as exc:
        why = ("rows of different lengths" if "inhomogeneous" in str(exc)
               else f"a value that is not an array ({type(exc).__name__})")
        raise ValueError(f"{name} must have shape {shape}, got {why}") from None


def _subgrid_table(value, name: str, rows: int, row_is: str) -> np.ndarray:
    """A table of explicit subgrid resolutions checked: ``rows`` rows of three whole numbers in
    [0, 2^31 - 1], a row all zeros (no subgrid) or all positive; as contiguous int32."""
    table = _as_array(value, name, f"({rows}, 3)")
    if table.shape != (rows, 3) or not np.issubdtype(table.dtype, np.integer):
        raise ValueError(f"{name} must be whole numbers of shape ({rows}, 3), one row per {row_is}, "
                         f"got {table.shape} {table.dtype}")
    if table.min(initial=0) < 0 or table.max(initial=0) > 2**31 - 1:
        raise ValueError(f"{name} must be between 0 (no subgrid) and 2^31 - 1")
    partial = (table == 0).any(axis=1) & (table != 0).any(axis=1)
    if partial.any():
        raise ValueError(f"{name} row {int(np.argmax(partial))} mixes zero and non-zero axes")
    return np.ascontiguousarray(table, dtype=np.int32)


def intersector_code(name: str) -> int:
    """The kernel code for an intersector name ('watertight' or 'moller-trumbore')."""
    key = _INTERSECTOR_ALIASES.get(str(name).lower(), str(name).lower())
    if key not in INTERSECTORS:
        raise ValueError(f"unknown intersector {name!r}; choose one of {', '.join(INTERSECTORS)}")
    return INTERSECTORS[key]


def _check_vertices_faces(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    v = _as_array(vertices, "vertices", "(V, 3)")
    f = _as_array(faces, "faces", "(F, 3)")
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must have shape (V, 3), got {v.shape}")
    if f.ndim != 2:
        raise ValueError(f"faces must have shape (F, 3), got {f.shape}")
    if f.shape[1] != 3:
        raise ValueError(f"faces must be triangles with 3 vertex indices each, got {f.shape[1]} per face")
    if f.shape[0] == 0:
        raise ValueError("the mesh is empty: it has no faces")
    if v.shape[0] == 0:
        raise ValueError("the mesh has faces but no vertices")
    if not (np.issubdtype(v.dtype, np.floating) or np.issubdtype(v.dtype, np.integer)):
        raise ValueError(f"vertices must be numbers, got dtype {v.dtype}")
    if not np.issubdtype(f.dtype, np.integer):
        if not (np.issubdtype(f.dtype, np.floating) and np.all(np.isfinite(f)) and np.all(f == np.round(f))):
            raise ValueError(f"faces must be integer vertex indices, got dtype {f.dtype}")
    v = np.ascontiguousarray(v, dtype=np.float64)
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        raise ValueError(f"{int(bad.sum())} vertices have NaN or Inf coordinates (first: vertex {int(np.argmax(bad))})")
    # range checks in the given dtype: uint64 past 2^63 or huge whole floats would wrap in int64
    if f.min() < 0:
        raise ValueError(f"face {int(np.argmin(f.min(axis=1)))} has a negative vertex index {int(f.min())}")
    if f.max() >= v.shape[0]:
        raise ValueError(
            f"face {int(np.argmax(f.max(axis=1)))} refers to vertex {int(f.max())}, "
            f"but the mesh has only {v.shape[0]} vertices")
    f = np.ascontiguousarray(f, dtype=np.int64)
    return v, f


def compiled_scene_stats(vertices, faces, *, threads: int = 2):
    """:func:`models.stats.scene_stats` with its pass over the triangles done by the kernels.

    The C pass (kernels/stats.c) mirrors the numpy reference term by term; the two
    agree to rounding (tests/test_stats_compiled.py) and share
    :func:`models.stats.stats_from_sums`, which turns the sums into statistics.
    ``threads=2`` runs the watertightness test beside the sums (both release the
    GIL; the result is the same either way), 1 runs them one after the other.
    """
    if threads not in (1, 2):
        raise ValueError(f"threads must be 1 or 2, got {threads!r}")
    from models.stats import aspect_sample_stride, stats_from_sums

    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    if f.ndim != 2 or f.shape[0] == 0:
        raise ValueError("mesh has no faces")
    stride = aspect_sample_stride(f.shape[0])
    if threads == 2:  # the two passes release the GIL: the edge grouping runs beside the sums
        with ThreadPoolExecutor(max_workers=1) as pool:
            topology = pool.submit(_kernels.mesh_topology, v, f)
            sums = _kernels.mesh_sums(v, f, stride)
            watertight, positions = topology.result()
    else:
        sums = _kernels.mesh_sums(v, f, stride)
        watertight, positions = _kernels.mesh_topology(v, f)
    return stats_from_sums(n_triangles=f.shape[0], box_lo=sums["box_lo"], box_hi=sums["box_hi"],
                           e1_axes=sums["e1"], e2_axes=sums["e2"], perimeters=sums["perimeters"],
                           pair_sums=sums["pair"], triple=sums["triple"], area=sums["area"], vol6=sums["vol6"],
                           n_good=sums["n_good"], aspect_sample=sums["aspect_sample"], watertight=watertight,
                           positions=positions)


def triangle_box_overlap(corners, lo, hi) -> np.ndarray:
    """:func:`models.nested.triangle_box_overlap` computed by the kernels' own test.

    corners (P, 3, 3), lo and hi (P, 3): pair p tests triangle ``corners[p]`` against the
    closed box ``[lo[p], hi[p]]``; returns (P,) bool.  The grid build uses the same test,
    so counts planned with it describe the grid the kernels build.
    """
    c = np.ascontiguousarray(corners, dtype=np.float64).reshape(-1, 9)
    return _kernels.triangle_box_overlap_many(c, np.ascontiguousarray(lo, dtype=np.float64),
                                              np.ascontiguousarray(hi, dtype=np.float64))


class Scene:
    """A triangle mesh ready for gridding.

    Parameters
    ----------
    vertices : (V, 3) float64
        Vertex positions (scene units).
    faces : (F, 3) int64
        Vertex indices of each triangle.
    name : str, optional
        A label for reports.
    """

    def __init__(self, vertices, faces, name: str | None = None):
        v, f = _check_vertices_faces(vertices, faces)
        v.setflags(write=False)
        f.setflags(write=False)
        self.vertices = v
        self.faces = f
        self.name = name or "mesh"
        used = v[f.reshape(-1)]
        lo, hi = grid_box(used.min(axis=0), used.max(axis=0))
        #: (3,) float64 corners of the grid box: the mesh's box, degenerate axes widened.
        self.box_lo = lo
        self.box_hi = hi
        self._stats = None

    @property
    def n_triangles(self) -> int:
        return int(self.faces.shape[0])

    @property
    def stats(self):
        """The scene statistics of :func:`models.stats.scene_stats` (computed once, in C)."""
        if self._stats is None:
            self._stats = compiled_scene_stats(self.vertices, self.faces)
        return self._stats

    def __repr__(self) -> str:
        return f"Scene({self.name!r}, {self.n_triangles} triangles)"

    @classmethod
    def from_file(cls, path) -> "Scene":
        """Load a mesh file: OBJ by gridcal's own reader (:mod:`calibrate._obj`), any
        other format trimesh reads (PLY, STL, OFF, glTF, ...) by trimesh.

        Raises ``ValueError`` naming the file when it is missing, unreadable,
        not a triangle mesh, or empty.
        """
        import trimesh

        try:
            p = Path(path)
        except TypeError:
            raise ValueError(f"path must be a mesh file's path (str or os.PathLike), got {_show(path)}") from None
        try:
            if not p.exists():
                raise ValueError(f"{p}: no such file")
            if p.is_dir():
                raise ValueError(f"{p}: is a directory, not a mesh file")
            if not os.access(p, os.R_OK):
                raise ValueError(f"{p}: not readable")
            if p.stat().st_size == 0:
                raise ValueError(f"{p}: the file is empty")
        except OSError as exc:  # e.g. a name too long for the file system
            raise ValueError(f"{p}: cannot access it ({exc.strerror or type(exc).__name__})") from None
        if p.suffix.lower() == ".obj":
            from ._obj import read_obj

            try:
                text = p.read_bytes().decode("utf-8", errors="strict")
            except UnicodeDecodeError:
                raise ValueError(f"{p}: not a text OBJ file (it is not UTF-8 text)") from None
            except OSError as exc:
                raise ValueError(f"{p}: cannot read it ({exc.strerror or type(exc).__name__})") from None
            vertices, faces = read_obj(text, source=str(p))
            if len(faces) == 0:
                raise ValueError(f"{p}: holds no triangles (is it a point cloud, or truncated?)")
            try:
                return cls(vertices, faces, name=p.name)
            except ValueError as exc:
                raise ValueError(f"{p}: {exc}") from None
        if p.suffix.lower() == ".stl":
            _check_binary_stl_length(p)
        try:
            with _quiet_trimesh():
                loaded = trimesh.load(str(p), force="mesh", process=False)
        except ImportError as exc:  # a format needing an optional package (pycollada, networkx, ...)
            raise ValueError(f"{p}: cannot read it as a mesh: trimesh needs an optional package for it "
                             f"({_reader_detail(exc)})") from None
        except Exception as exc:  # trimesh raises many types for a corrupt file
            raise ValueError(f"{p}: cannot read it as a mesh; is it corrupt or truncated? "
                             f"({_reader_detail(exc)})") from None
        if isinstance(loaded, list):
            loaded = [m for m in loaded if hasattr(m, "faces")]
            if not loaded:
                raise ValueError(f"{p}: holds no triangle mesh")
            loaded = trimesh.util.concatenate(loaded)
        faces = getattr(loaded, "faces", None)
        vertices = getattr(loaded, "vertices", None)
        if faces is None or vertices is None or len(faces) == 0:
            raise ValueError(f"{p}: holds no triangles (is it a point cloud, or truncated?)")
        try:
            return cls(np.asarray(vertices), np.asarray(faces), name=p.name)
        except ValueError as exc:
            raise ValueError(f"{p}: {exc}") from None

    @classmethod
    def builtin(cls, name: str) -> "Scene":
        """One of the built-in procedural scenes (see :mod:`calibrate.scenes`)."""
        from .scenes import load_builtin

        v, f = load_builtin(name)
        return cls(v, f, name=name)

    @classmethod
    def load(cls, spec) -> "Scene":
        """A built-in scene's name or a mesh file's path."""
        if isinstance(spec, Scene):
            return spec
        from .scenes import builtin_names

        if str(spec) in builtin_names():
            return cls.builtin(str(spec))
        if not Path(str(spec)).exists() and os.sep not in str(spec) and "." not in str(spec):
            raise ValueError(
                f"{spec!r} is neither a mesh file nor a built-in scene; built-in scenes: "
                f"{', '.join(builtin_names())}")
        return cls.from_file(spec)


#: Binary STL layout: an 80-byte header, a uint32 triangle count, 50 bytes per triangle.
STL_HEADER_BYTES = 84
STL_TRIANGLE_BYTES = 50
#: Longest reader message quoted in an error (the rest is cut).
MAX_DETAIL_CHARS = 80


def _check_binary_stl_length(p: Path) -> None:
    """A binary STL shorter than its header's triangle count says is truncated: say so.

    (trimesh would fall back to reading it as ASCII and fail with an unrelated
    message.)  An ASCII STL starts with ``solid``; a binary one whose header also
    starts with ``solid`` is recognised by its exact length.
    """
    size = p.stat().st_size
    with open(p, "rb") as fh:
        head = fh.read(STL_HEADER_BYTES)
    if size >= STL_HEADER_BYTES:
        count = int.from_bytes(head[80:84], "little")
        expected = STL_HEADER_BYTES + STL_TRIANGLE_BYTES * count
        if size >= expected:
            return  # a complete binary STL (trailing bytes are ignored), or ASCII
    if head.lstrip().lower().startswith(b"solid"):
        return  # ASCII STL: trimesh reads it and says when it holds no triangles
    if size < STL_HEADER_BYTES:
        raise ValueError(f"{p}: truncated binary STL: {size} bytes, but its header alone is "
                         f"{STL_HEADER_BYTES} bytes")
    raise ValueError(f"{p}: truncated binary STL: its header announces {count:,} triangles "
                     f"({expected:,} bytes), but the file has {size:,} bytes")


def _reader_detail(exc: BaseException) -> str:
    """A reader's exception as a short phrase for a one-line message."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    if len(text) > MAX_DETAIL_CHARS:
        text = text[:MAX_DETAIL_CHARS - 3].rstrip() + "..."
    return f"{type(exc).__name__}: {text}"


class _quiet_trimesh:
    """Hold back trimesh's log records while it reads a file.

    trimesh logs warnings about the files it reads; with no logging configured
    Python prints them on stderr, where a user mistake must be one line. The
    error raised afterwards says what went wrong.
    """

    def __enter__(self):
        import logging

        self._logger = logging.getLogger("trimesh")
        self._level = self._logger.level
        self._logger.setLevel(logging.CRITICAL + 1)
        return self

    def __exit__(self, *exc):
        self._logger.setLevel(self._level)
        return False


def _check_rays(origins, directions) -> tuple[np.ndarray, np.ndarray]:
    o = _as_array(origins, "origins", "(n, 3)")
    d = _as_array(directions, "directions", "(n, 3)")
    for name, a in (("origins", o), ("directions", d)):
        if a.ndim != 2 or a.shape[1] != 3:
            raise ValueError(f"{name} must have shape (n, 3), got {a.shape}")
        if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
            raise ValueError(f"{name} must be numbers, got dtype {a.dtype}")
    if o.shape[0] != d.shape[0]:
        raise ValueError(f"origins and directions differ in length: {o.shape[0]} and {d.shape[0]} rays")
    o = np.ascontiguousarray(o, dtype=np.float64)
    d = np.ascontiguousarray(d, dtype=np.float64)
    for name, a in (("origins", o), ("directions", d)):
        bad = ~np.isfinite(a).all(axis=1)
        if bad.any():
            raise ValueError(f"{name} of {int(bad.sum())} rays contain NaN or Inf (first: ray {int(np.argmax(bad))})")
    zero = ~(d != 0).any(axis=1)
    if zero.any():
        raise ValueError(f"{int(zero.sum())} rays have a zero direction (first: ray {int(np.argmax(zero))})")
    return o, d


def _whole(x) -> int | None:
    """A real, non-bool number x as an int when it is whole and finite, else None."""
    if not _is_real(x):
        return None
    if isinstance(x, numbers.Integral):
        return int(x)
    try:
        f = float(x)
    except (OverflowError, ValueError):
        return None
    return int(f) if math.isfinite(f) and f == math.floor(f) else None


def _show_axis(n: int) -> str:
    """An axis's cell count; past MAX_PRINTED_AXIS_DIGITS digits as 3 significant digits (1e+300)."""
    digits = str(abs(n))
    if len(digits) <= MAX_PRINTED_AXIS_DIGITS:
        return str(n)
    mantissa = digits[0] + ("." + digits[1:3]).rstrip("0").rstrip(".")
    return f"{'-' if n < 0 else ''}{mantissa}e+{len(digits) - 1}"


def _show_axes(res) -> str:
    """'nx x ny x nz' for a message (huge axes shortened by _show_axis)."""
    return "x".join(_show_axis(n) for n in res)


def _check_resolution(resolution, what="resolution") -> tuple[int, int, int]:
    bad = ValueError(f"{what} must be three whole numbers (nx, ny, nz), got {_show(resolution)}")
    if isinstance(resolution, (str, bytes)):
        raise bad
    try:
        items = list(resolution)
    except TypeError:
        raise bad from None
    res = tuple(_whole(x) for x in items)
    if len(res) != 3 or None in res:
        raise bad
    if min(res) < 1:
        raise ValueError(f"{what} {_show_axes(res)}: every axis needs at least 1 cell")
    if max(res) > MAX_AXIS_CELLS:
        raise ValueError(f"{what} {_show_axes(res)}: an axis exceeds 2^31 - 1 cells")
    return res


def _positive_finite(x) -> bool:
    """x is a real, non-bool number, finite and > 0."""
    if not _is_real(x):
        return False
    try:
        f = float(x)
    except (OverflowError, ValueError):
        return False
    return math.isfinite(f) and f > 0


def _list_or_none(values) -> list | None:
    try:
        return list(values)
    except TypeError:
        return None


def manta_rule(levels: int, scale: float = MANTA_SCALE) -> tuple[list[float], list[float]]:
    """Per-depth (scale, exponent) of Manta's RecursiveGrid rule for an L-level grid.

    A (sub)grid at depth d over n references gets (scale * n)^(3 / (2L + 1 - 2d))
    cells in all (Ize, Shirley and Parker 2007; Manta used scale 8).
    """
    scales = [float(scale)] * MAX_LEVELS
    exponents = [1.0] * MAX_LEVELS
    for d in range(min(levels, MAX_LEVELS)):
        exponents[d] = 3.0 / (2 * levels + 1 - 2 * d)
    return scales, exponents


def resolution_for_cells(total_cells: float, extent) -> tuple[int, int, int]:
    """Near-cubic cells: n_i = d_i * cbrt(M / (d_x d_y d_z)), rounded, each >= 1 (log space)."""
    e = np.asarray(extent, dtype=np.float64)
    logs = np.log(e) + (math.log(max(total_cells, 1.0)) - np.log(e).sum()) / 3.0
    return tuple(int(max(1, min(2**31 - 1, round(math.exp(min(x, 40.0)))))) for x in logs)


class Grid:
    """A built grid over a :class:`Scene`.  Build with :meth:`uniform` or :meth:`nested`."""

    def __init__(self, scene: Scene, capsule, options: dict):
        self.scene = scene
        self._capsule = capsule
        self.options = options
        self._info = _kernels.info(capsule)

    # -- construction -------------------------------------------------------------
    @classmethod
    def _build(cls, scene: Scene, resolution, *, intersector, mailbox, insertion, levels, threshold,
               level_scale, level_exponent, subgrid_resolutions, rule_max_axis, memory_limit, threads,
               subgrid_resolutions2=None):
        if not isinstance(scene, Scene):
            raise ValueError(f"scene must be a calibrate.Scene, got {type(scene).__name__}")
        res = _check_resolution(resolution)
        if not isinstance(insertion, str) or insertion not in INSERTIONS:
            raise ValueError(f"unknown insertion {_show(insertion)}; choose one of {', '.join(INSERTIONS)}")
        if memory_limit is not None:
            memory_limit = _whole_number(memory_limit, "memory_limit (bytes)", 1, MAX_INT64, "2^63 - 1")
        mailbox = _flag(mailbox, "mailbox")
        threads = _whole_number(threads, "threads", 1, MAX_BUILD_THREADS, str(MAX_BUILD_THREADS))
        box = list(scene.box_lo) + list(scene.box_hi)
        options = dict(resolution=res, intersector=intersector, mailbox=mailbox, insertion=insertion,
                       levels=levels, threshold=threshold)
        try:
            cap = _kernels.build(
                scene.vertices, scene.faces, res, intersector=intersector_code(intersector),
                insertion=INSERTIONS[insertion], mailbox=mailbox, box=box,
                memory_limit=int(memory_limit or 0), levels=int(levels), threshold=int(threshold),
                level_scale=level_scale, level_exponent=level_exponent,
                subgrid_resolutions=subgrid_resolutions, rule_max_axis=int(rule_max_axis),
                threads=threads, subgrid_resolutions2=subgrid_resolutions2)
        except (OverflowError, MemoryError) as exc:
            raise ValueError(f"cannot build the grid: {exc}") from None
        return cls(scene, cap, options)

    @classmethod
    def uniform(cls, scene: Scene, resolution, intersector: str = "watertight", mailbox: bool = False,
                insertion: str = "exact", memory_limit: int | None = None,
                threads: int = DEFAULT_BUILD_THREADS) -> "Grid":
        """A uniform grid of ``resolution = (nx, ny, nz)`` cells over the scene's grid box.

        ``insertion='exact'`` stores a triangle in the cells it overlaps (separating
        axis test); ``'bounds'`` in every cell its bounding box overlaps.  A
        resolution that overflows 32-bit cell offsets or passes ``memory_limit``
        (bytes; default 8 GiB) raises ``ValueError``.  ``threads`` (1 to 64) splits the
        build's passes over triangles and references into that many parts run at
        once; the grid is the same for any number.
        """
        scales, exps = manta_rule(1)
        return cls._build(scene, resolution, intersector=intersector, mailbox=mailbox, insertion=insertion,
                          levels=1, threshold=DEFAULT_SUBDIVIDE_THRESHOLD, level_scale=scales,
                          level_exponent=exps, subgrid_resolutions=None,
                          rule_max_axis=DEFAULT_RULE_MAX_AXIS, memory_limit=memory_limit, threads=threads)

    @classmethod
    def nested(cls, scene: Scene, levels: int = 2, resolution=None, *, scale: float = MANTA_SCALE,
               exponents=None, threshold: int = DEFAULT_SUBDIVIDE_THRESHOLD, subgrid_resolutions=None,
               subgrid_resolutions2=None, rule_max_axis: int = DEFAULT_RULE_MAX_AXIS, intersector: str = "watertight",
               mailbox: bool = False, insertion: str = "exact", memory_limit: int | None = None,
               threads: int = DEFAULT_BUILD_THREADS) -> "Grid":
        """A nested grid of ``levels`` levels (1 = uniform).

        The top level has ``resolution`` (default: the rule applied to all N
        triangles).  Below it, a cell with more than ``threshold`` references
        gets a subgrid over that cell with total cells (scale * n)^exponent,
        where n is the cell's reference count and exponent defaults to Manta's
        3 / (2L + 1 - 2 depth); or, at depth 1, the explicit per-cell
        ``subgrid_resolutions`` ((nx*ny*nz, 3) int, x fastest; a row of zeros
        means no subgrid), deeper levels following the rule; and at depth 2 the
        explicit ``subgrid_resolutions2`` (with ``subgrid_resolutions`` and
        ``levels >= 3``): one row for every cell of every depth-1 subgrid, the
        subgrids in the order of their top cells and each one's cells x fastest (a row
        of zeros: no subgrid).  ``threads`` as for :meth:`uniform`.
        """
        levels = _whole_number(levels, "levels", 1, MAX_LEVELS, str(MAX_LEVELS))
        if not _positive_finite(scale):
            raise ValueError(f"scale must be a positive number, got {_show(scale)}")
        threshold = _whole_number(threshold, "threshold", 0, MAX_SUBDIVIDE_THRESHOLD, "2^32 - 2")
        rule_max_axis = _whole_number(rule_max_axis, "rule_max_axis", 1, MAX_AXIS_CELLS, "2^31 - 1")
        scales, exps = manta_rule(levels, float(scale))
        if exponents is not None:
            items = None if isinstance(exponents, (str, bytes)) else _list_or_none(exponents)
            if items is None or len(items) != levels or not all(_positive_finite(e) for e in items):
                raise ValueError(f"exponents needs {levels} positive numbers, one per level, got {_show(exponents)}")
            exps[:levels] = [float(e) for e in items]
        if not isinstance(scene, Scene):
            raise ValueError(f"scene must be a calibrate.Scene, got {type(scene).__name__}")
        if resolution is None:
            total = (scales[0] * scene.n_triangles) ** exps[0]
            resolution = resolution_for_cells(total, scene.box_hi - scene.box_lo)
        res = _check_resolution(resolution)
        sub = None
        if subgrid_resolutions is not None:
            ncell = res[0] * res[1] * res[2]
            sub = _subgrid_table(subgrid_resolutions, "subgrid_resolutions", ncell, "top-level cell")
            if levels < 2:
                raise ValueError("subgrid_resolutions needs levels >= 2")
        sub2 = None
        if subgrid_resolutions2 is not None:
            if sub is None or levels < 3:
                raise ValueError("subgrid_resolutions2 needs subgrid_resolutions and levels >= 3")
            full = (sub > 0).all(axis=1)
            rows = int(np.prod(sub[full].astype(np.int64), axis=1).sum())
            sub2 = _subgrid_table(subgrid_resolutions2, "subgrid_resolutions2", rows, "cell of the depth-1 subgrids")
        return cls._build(scene, res, intersector=intersector, mailbox=mailbox, insertion=insertion,
                          levels=int(levels), threshold=int(threshold), level_scale=scales,
                          level_exponent=exps, subgrid_resolutions=sub, rule_max_axis=rule_max_axis,
                          memory_limit=memory_limit, threads=threads, subgrid_resolutions2=sub2)

    # -- properties ---------------------------------------------------------------
    @property
    def info(self) -> dict:
        """Cells, references, empty cells, memory (bytes), levels, resolution, box."""
        return dict(self._info)

    @property
    def resolution(self) -> tuple[int, int, int]:
        return tuple(self._info["resolution"])

    def top_counts(self) -> np.ndarray:
        """(nz, ny, nx) int64: references per top-level cell (whole subtree for a subgrid)."""
        return _kernels.top_counts(self._capsule)

    def __repr__(self) -> str:
        i = self._info
        return (f"Grid({self.scene.name!r}, {i['resolution'][0]}x{i['resolution'][1]}x{i['resolution'][2]}, "
                f"levels={i['levels']}, cells={i['n_cells']}, refs={i['n_refs']})")

    # -- tracing ------------------------------------------------------------------
    def intersect(self, origins, directions) -> tuple[np.ndarray, np.ndarray]:
        """First hits with the timed twin.

        Parameters
        ----------
        origins, directions : (n, 3) float64
            Rays; directions need not be unit length (t is in their units).

        Returns
        -------
        t : (n,) float64, +inf on a miss;  prim : (n,) int32, -1 on a miss.
        Hits count for t > 0.
        """
        o, d = _check_rays(origins, directions)
        return _kernels.intersect(self._capsule, o, d)

    def count(self, origins, directions, hits: bool = False, visits: bool = False, changes: bool = False):
        """Per-ray work from the instrumented twin.

        Returns ``(steps, tests, subgrids)``, each (n,) uint32: cells visited at
        every level, triangle tests, subgrids entered.  With ``hits=True``,
        ``(t, prim)`` come first: the same hits as :meth:`intersect`.  With
        ``visits=True``, the occupied cells entered follow: the cells holding
        triangles that each ray's walk tested, at every level (a cell holding a
        subgrid is not one; its own cells are), part of ``steps``.  With
        ``changes=True``, the occupancy changes come last: the cells of each walk
        (the top grid's or a subgrid's) empty after a non-empty one or non-empty
        after an empty one, the cell before a walk's first counting as non-empty
        (a cell holding a subgrid is non-empty); at most ``steps``.  One walk
        counts them all.
        """
        hits = _flag(hits, "hits")
        visits = _flag(visits, "visits")
        changes = _flag(changes, "changes")
        o, d = _check_rays(origins, directions)
        t, prim, steps, tests, subgrids, n_visits, n_changes = _kernels.count(self._capsule, o, d)
        out = (t, prim) if hits else ()
        out += (steps, tests, subgrids)
        if visits:
            out += (n_visits,)
        return out + (n_changes,) if changes else out

    def count_visits(self, origins, directions) -> np.ndarray:
        """Occupied cells entered per ray, (n,) uint32: :meth:`count`'s last result with ``visits=True``."""
        return self.count(origins, directions, visits=True)[-1]

    def bench(self, origins, directions, loops: int = 1) -> tuple[int, float]:
        """Trace the batch ``loops`` times in C; returns (elapsed ns, checksum)."""
        o, d = _check_rays(origins, directions)
        loops = _whole_number(loops, "loops", 1, MAX_INT64, "2^63 - 1")
        return _kernels.bench(self._capsule, o, d, loops)

    def timed_batch(self, origins, directions, clock: str = "wall"):
        """A ``run(loops) -> (elapsed_ns, checksum)`` callable for :func:`calibrate.protocol.measure`.

        Its ``prime()`` traces the batch's first :data:`PRIME_RAYS` rays once, untimed
        (what :func:`calibrate.protocol.measure` calls before each value when priming).

        clock : ``"wall"``, the kernel's own monotonic clock around its loop, or
            ``"thread"``, the calling thread's CPU time around the same loop (the
            kernel runs in the calling thread): a value then leaves out the time the
            thread waited for a core, which on a busy host is most of the noise.
        """
        o, d = _check_rays(origins, directions)
        cap = self._capsule
        if clock not in TIMING_CLOCKS:
            raise ValueError(f"clock must be one of {', '.join(TIMING_CLOCKS)}, got {_show(clock)}")

        def run(loops: int):
            return _kernels.bench(cap, o, d, _whole_number(loops, "loops", 1, MAX_INT64, "2^63 - 1"))

        po, pd = np.ascontiguousarray(o[:PRIME_RAYS]), np.ascontiguousarray(d[:PRIME_RAYS])

        def prime():
            _kernels.bench(cap, po, pd, 1)

        if clock == "wall":
            run.prime = prime
            return run
        read = time.thread_time_ns

        def run_thread(loops: int):
            t0 = read()
            _, checksum = run(loops)
            return read() - t0, checksum

        run_thread.prime = prime
        return run_thread


def brute_force(scene: Scene, origins, directions, intersector: str = "watertight"):
    """Reference first hits: every ray against every triangle.  Returns (t, prim) like Grid.intersect."""
    if not isinstance(scene, Scene):
        raise ValueError(f"scene must be a calibrate.Scene, got {type(scene).__name__}")
    o, d = _check_rays(origins, directions)
    return _kernels.brute_force(scene.vertices, scene.faces, intersector_code(intersector), o, d)


def empty_grid(box_lo, box_hi, resolution, intersector: str = "watertight") -> Grid:
    """A grid with no triangles over a box: times set-up and stepping alone (T_setup, T_step)."""
    res = _check_resolution(resolution)
    corners = []
    for name, corner in (("box_lo", box_lo), ("box_hi", box_hi)):
        a = _as_array(corner, name, "(3,)")
        if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
            raise ValueError(f"{name} must be numbers (x, y, z), got {_show(corner)}")
        if a.shape != (3,):
            raise ValueError(f"{name} must have shape (3,), got {a.shape}")
        corners.append(a.astype(np.float64))
    lo, hi = corners
    scene = Scene.__new__(Scene)
    scene.vertices = np.zeros((1, 3))
    scene.faces = np.zeros((0, 3), dtype=np.int64)
    scene.name = "empty"
    scene.box_lo, scene.box_hi = lo, hi
    scene._stats = None
    try:
        cap = _kernels.build(scene.vertices, scene.faces, res, intersector=intersector_code(intersector),
                             box=list(lo) + list(hi))
    except (OverflowError, MemoryError) as exc:
        raise ValueError(f"cannot build the grid: {exc}") from None
    return Grid(scene, cap, dict(resolution=res, intersector=intersector, mailbox=False, insertion="exact",
                                 levels=1, threshold=DEFAULT_SUBDIVIDE_THRESHOLD))
