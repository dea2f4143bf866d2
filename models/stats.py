"""Scene statistics: the few sums over a triangle mesh that the cost models need.

Everything here is vectorised over triangles (one pass of numpy over the
``(F, 3, 3)`` corner array); no per-triangle Python loop.

Inputs everywhere are ``vertices : (V, 3) float64`` (scene units) and
``faces : (F, 3) int64`` (indices into ``vertices``).

The sums (DESIGN §3.2), per triangle T with bounding-box extent ``ext_T`` (3,),
area ``A_T`` and unit normal ``n_T``:

- ``E1 = sum_T |ext_T|_1``; per axis ``e1_axes[i] = sum_T ext_T[i]``.
- ``E2 = sum_T A_T |n_T|_1``; per axis ``e2_axes[i] = sum_T A_T |n_T[i]|``
  (the area of T projected along axis i).
- ``perimeters[i] = sum_T P_i(T)``, the perimeter of T projected along axis i
  (the mailbox hull term, :mod:`models.general`).
- ``bbox_pair_sums = [sum ext_y ext_z, sum ext_z ext_x, sum ext_x ext_y]`` and
  ``bbox_triple_sum = sum ext_x ext_y ext_z``: the extra sums needed when a grid
  build assigns triangles to cells by bounding-box overlap instead of exact overlap.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# --- grid box rule ---------------------------------------------------------------
#: An axis thinner than this fraction of the longest extent is widened to it, so a
#: flat scene still gets a grid box of positive volume (cells stay well defined).
MIN_EXTENT_FRACTION = 1e-3
#: For a scene collapsed to one point, every axis is widened to this fraction of the
#: largest absolute coordinate ...
POINT_SCENE_EXTENT_FRACTION = 1e-6
#: ... and never below this absolute extent (scene units), so the origin works too.
MIN_ABSOLUTE_EXTENT = 1e-300
#: Smallest box volume the statistics accept (the smallest normal double): below it the
#: volume and the k of the closed forms lose all precision.
MIN_NORMAL_VOLUME = float(np.finfo(np.float64).tiny)
#: Extents of a cube whose statistics stay finite and normal (volume and surface), for messages.
MIN_STATS_EXTENT = 1e-100
MAX_STATS_EXTENT = 1e100

# --- triangle shape ----------------------------------------------------------------
#: A triangle is degenerate when 2*area <= this * (longest edge)^2, i.e. its aspect
#: ratio longest_edge^2 / (2 area) exceeds 1e12 (or all its edges have zero length).
DEGENERATE_REL_AREA = 1e-12

# --- scene class (paper fidelity), from the aspect-ratio distribution ------------------
# AR = longest_edge^2 / (2 area): 1.155 equilateral, 2.0 right isosceles (a split
# square).  The talk calls "long skinny" triangles lines and compact ones points.
#: Compact when the median AR is at most this ...
AR_COMPACT_MEDIAN_MAX = 4.0
#: ... and the 95th percentile at most this.
AR_COMPACT_P95_MAX = 16.0
#: Long skinny when the median AR is at least this.
AR_SKINNY_MEDIAN_MIN = 10.0
#: Long skinny too when more than this fraction of the triangles is degenerate (segments).
DEGENERATE_FRACTION_SKINNY = 0.5


def _check_mesh(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must have shape (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"faces must have shape (F, 3), got {f.shape}")
    if f.shape[0] == 0:
        raise ValueError("mesh has no faces")
    if not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces must be integer indices, got dtype {f.dtype}")
    v = v.astype(np.float64, copy=False)
    if not np.all(np.isfinite(v)):
        raise ValueError("vertices contain NaN or Inf")
    if f.min() < 0 or f.max() >= v.shape[0]:
        raise ValueError(f"face indices out of range [0, {v.shape[0]})")
    return v, f.astype(np.int64, copy=False)


def grid_box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """The grid box for a scene bounding box: positive extents, finite values.

    Parameters
    ----------
    lo, hi : (3,) float64
        Scene bounding box corners (scene units), ``lo <= hi``.

    Returns
    -------
    (lo, hi) : two (3,) float64 arrays, ``hi - lo > 0`` on every axis.

    Rule (shared with the C grid, which receives this box from Python):
    ``e_i = hi_i - lo_i``, ``emax = max e_i``.  If ``emax > 0``, every axis with
    ``e_i < MIN_EXTENT_FRACTION * emax`` is widened symmetrically about its centre to
    that width.  If ``emax == 0`` (one point), every axis is widened to
    ``max(POINT_SCENE_EXTENT_FRACTION * max|coord|, MIN_ABSOLUTE_EXTENT)``.
    If rounding of ``centre +- width/2`` would swallow the widening (huge
    coordinates), the axis is widened by whole ulps until its extent is positive.
    """
    lo = np.array(lo, dtype=np.float64).reshape(-1)
    hi = np.array(hi, dtype=np.float64).reshape(-1)
    if lo.shape != (3,) or hi.shape != (3,):
        raise ValueError(f"box corners must have shape (3,), got {lo.shape} and {hi.shape}")
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError("box corners contain NaN or Inf")
    if np.any(hi < lo):
        raise ValueError(f"box has hi < lo: lo={lo}, hi={hi}")
    with np.errstate(over="ignore"):
        ext = hi - lo
    if not np.all(np.isfinite(ext)):
        raise ValueError(f"box is too wide for float64: its extent overflows (lo={lo.tolist()}, hi={hi.tolist()})")
    emax = float(ext.max())
    if emax > 0.0:
        width = MIN_EXTENT_FRACTION * emax
    else:
        width = max(POINT_SCENE_EXTENT_FRACTION * float(np.abs(np.concatenate([lo, hi])).max()),
                    MIN_ABSOLUTE_EXTENT)
    thin = ext < width
    centre = 0.5 * lo + 0.5 * hi  # no overflow near the float64 limit
    new_lo = np.where(thin, centre - 0.5 * width, lo)
    new_hi = np.where(thin, centre + 0.5 * width, hi)
    # Guarantee strictly positive extents even when width/2 is below one ulp.
    for _ in range(64):
        bad = ~(new_hi - new_lo > 0.0)
        if not bad.any():
            break
        new_lo = np.where(bad, np.nextafter(new_lo, -np.inf), new_lo)
        new_hi = np.where(bad, np.nextafter(new_hi, np.inf), new_hi)
    if not (np.all(np.isfinite(new_lo)) and np.all(np.isfinite(new_hi))):
        raise ValueError("box is too close to the float64 limit to widen")
    return new_lo, new_hi


@dataclass(frozen=True)
class TriangleGeometry:
    """Per-triangle quantities, all arrays of length F (scene units)."""

    lo: np.ndarray  # (F, 3) bounding-box min corner
    hi: np.ndarray  # (F, 3) bounding-box max corner
    area: np.ndarray  # (F,) area
    proj_area: np.ndarray  # (F, 3) area projected along each axis = A |n_i|
    proj_perimeter: np.ndarray  # (F, 3) perimeter projected along each axis
    longest_edge_sq: np.ndarray  # (F,) squared longest edge
    degenerate: np.ndarray  # (F,) bool

    @property
    def ext(self) -> np.ndarray:
        """(F, 3) bounding-box extents."""
        return self.hi - self.lo


#: Triangles per chunk of the one-pass accumulation (keeps temporaries in cache).
CHUNK_TRIANGLES = 2 ** 14
#: Above this many triangles the aspect-ratio percentiles are estimated from an evenly
#: strided sample of about this many triangles (the degenerate count stays exact).
AR_SAMPLE_TRIANGLES = 2 ** 17


def _columns(v, f):
    """(3, V) coordinate rows and the three face-corner index columns (contiguous)."""
    return np.ascontiguousarray(v.T), [np.ascontiguousarray(f[:, j]) for j in range(3)]


def _chunk_geometry(v3, corners, a, b):
    """Per-triangle quantities for triangles a..b, as (3, n) blocks (axis first).

    Returns lo (3, n), hi (3, n), cross (3, n) = (p1-p0) x (p2-p0) (so the projected
    areas are |cross| / 2), proj_perimeter (3, n), area (n,), longest_sq (n,), p0 (3, n).
    """
    p0, p1, p2 = (np.take(v3, c[a:b], axis=1) for c in corners)
    lo = np.minimum(np.minimum(p0, p1), p2)
    hi = np.maximum(np.maximum(p0, p1), p2)
    u, w, e1 = p1 - p0, p2 - p0, p2 - p1
    cross = np.empty_like(u)
    cross[0] = u[1] * w[2] - u[2] * w[1]
    cross[1] = u[2] * w[0] - u[0] * w[2]
    cross[2] = u[0] * w[1] - u[1] * w[0]
    area = 0.5 * np.sqrt(np.einsum("ij,ij->j", cross, cross))
    sq = [u * u, e1 * e1, w * w]  # squared edge components, (3, n) each
    tot = [x.sum(axis=0) for x in sq]  # squared edge lengths
    # Perimeter of T projected along axis i: sum over edges of the length without component i.
    proj_perimeter = sum(np.sqrt(np.maximum(t - x, 0.0)) for t, x in zip(tot, sq, strict=True))
    longest_sq = np.maximum(np.maximum(tot[0], tot[1]), tot[2])
    return lo, hi, cross, proj_perimeter, area, longest_sq, p0


def triangle_geometry(vertices, faces) -> "TriangleGeometry":
    """Per-triangle bounding boxes, areas, projected areas and perimeters (vectorised)."""
    v, f = _check_mesh(vertices, faces)
    v3, corners = _columns(v, f)
    lo, hi, cross, pp, area, lsq, _ = _chunk_geometry(v3, corners, 0, f.shape[0])
    degenerate = ~(2.0 * area > DEGENERATE_REL_AREA * lsq)  # also catches 0 <= 0
    return TriangleGeometry(lo=np.ascontiguousarray(lo.T), hi=np.ascontiguousarray(hi.T), area=area,
                            proj_area=np.ascontiguousarray(0.5 * np.abs(cross.T)),
                            proj_perimeter=np.ascontiguousarray(pp.T), longest_edge_sq=lsq, degenerate=degenerate)


#: splitmix64 constants (Steele, Lea, Flood 2014) for hashing vertex positions.
_SPLITMIX_GAMMA = 0x9E3779B97F4A7C15
_SPLITMIX_M1 = 0xBF58476D1CE4E5B9
_SPLITMIX_M2 = 0x94D049BB133111EB


def _splitmix(x):
    """splitmix64 finaliser on a uint64 array (wrapping arithmetic)."""
    x = x ^ (x >> np.uint64(30))
    x = x * np.uint64(_SPLITMIX_M1)
    x = x ^ (x >> np.uint64(27))
    x = x * np.uint64(_SPLITMIX_M2)
    return x ^ (x >> np.uint64(31))


def _merge_positions(v) -> np.ndarray:
    """(V,) id per vertex, equal iff positions are bit-equal (after -0.0 -> +0.0).

    Hashes the coordinate bits (one 1-D sort instead of a row sort) and verifies that
    every vertex equals its hash representative; on a collision falls back to the
    exact row-wise ``np.unique``.
    """
    cols = [np.ascontiguousarray(v[:, i]) + 0.0 for i in range(3)]  # -0.0 -> +0.0: equal bits
    g = np.uint64(_SPLITMIX_GAMMA)
    with np.errstate(over="ignore"):
        h = _splitmix(cols[0].view(np.uint64) + g)
        h = _splitmix(h ^ cols[1].view(np.uint64))
        h = _splitmix(h ^ cols[2].view(np.uint64))
    _, inverse = np.unique(h, return_inverse=True)  # no return_index: keeps the fast unstable sort
    inverse = inverse.reshape(-1)
    rep = np.empty(int(inverse.max()) + 1, dtype=np.int64)
    rep[inverse] = np.arange(inverse.size)  # any member of each hash class
    idx = rep[inverse]
    if all(np.array_equal(c[idx], c) for c in cols):  # column gathers: no row fancy-indexing
        return inverse
    _, inverse = np.unique(v, axis=0, return_inverse=True)
    return inverse.reshape(-1)


def is_watertight(vertices, faces) -> bool:
    """True when every edge is shared by exactly two faces after merging identical positions.

    Vertices at identical positions (bit-equal float64 coordinates) are merged
    first, so a mesh stored with split vertices (per-face normals/UVs) still counts.
    """
    return mesh_topology(vertices, faces)[0]


def mesh_topology(vertices, faces) -> tuple[bool, int]:
    """(watertight, distinct vertex positions): :func:`is_watertight`, and the number of
    distinct positions among all the vertices given (referenced or not)."""
    v, f = _check_mesh(vertices, faces)
    ids = _merge_positions(v)
    return _edges_twice(ids, f), int(ids.max()) + 1


def _edges_twice(ids, f) -> bool:
    """Every edge of faces f, over merged vertex ids, shared by exactly two faces."""
    g = [ids[np.ascontiguousarray(f[:, j])] for j in range(3)]  # merged vertex ids per corner
    a = np.concatenate(g)
    b = np.concatenate([g[1], g[2], g[0]])
    key = np.minimum(a, b) * np.int64(int(ids.max()) + 1) + np.maximum(a, b)
    key.sort()
    # Every key exactly twice: pairs (0,1), (2,3), ... equal, and neighbouring pairs differ.
    return bool(np.array_equal(key[0::2], key[1::2]) and np.all(key[2::2] != key[1:-1:2]))


@dataclass(frozen=True)
class TerminationSample:
    """Where isotropic lines through the grid box stop on the real mesh (a Monte Carlo sample).

    fraction : the box chord the rays cover before their first hit, summed over the rays,
        over the chords summed (a ray that misses covers its whole chord), in [0, 1]:
        the traversed fraction of :class:`models.general.Terms`.
    p_hit : the fraction of the rays that hit.
    rays : how many were traced.
    resolution, occupied : optional, the grid the rays were traced through (nx, ny, nz)
        and how many of its cells hold a triangle: what
        :func:`models.general.occupied_cells` scales its count by (both or neither).
    visits : optional (with ``resolution``), the occupied cells the rays entered before
        their hit in that grid, per ray: what :func:`models.general.surface_visits` takes
        a surface's count from.
    occupancy : optional (with ``resolution``), more grids of the mesh and their occupied
        cells, ``((nx, ny, nz), occupied)`` each: :func:`models.general.occupancy_scale`
        interpolates its scale between the grids' sizes.
    changes : optional (with ``resolution``), grids of the mesh (the sample's among them) and
        the changes of occupancy per ray along the walks of the rays in each,
        ``((nx, ny, nz), changes)``: what :func:`models.general.occupancy_changes`
        interpolates between the grids' sizes.
    """

    fraction: float
    p_hit: float
    rays: int
    resolution: tuple[int, int, int] | None = None
    occupied: int | None = None
    visits: float | None = None
    occupancy: tuple = ()
    changes: tuple = ()

    def __post_init__(self):
        if not (0.0 <= self.fraction <= 1.0 and 0.0 <= self.p_hit <= 1.0):
            raise ValueError(f"fraction and p_hit must lie in [0, 1], got {self.fraction!r}, {self.p_hit!r}")
        if isinstance(self.rays, bool) or not (isinstance(self.rays, int) and self.rays >= 1):
            raise ValueError(f"rays must be a whole number >= 1, got {self.rays!r}")
        if (self.resolution is None) != (self.occupied is None):
            raise ValueError("resolution and occupied come together (the sample's grid and its occupied cells)")
        if self.resolution is not None:
            _check_grid_cells(self.resolution, self.occupied)
        if self.visits is not None:
            if self.resolution is None:
                raise ValueError("visits need the sample's grid (resolution and occupied)")
            if isinstance(self.visits, bool) or not (isinstance(self.visits, (int, float))
                                                     and math.isfinite(self.visits) and self.visits >= 0):
                raise ValueError(f"visits must be a finite number >= 0, got {self.visits!r}")
        if self.occupancy and self.resolution is None:
            raise ValueError("occupancy needs the sample's grid (resolution and occupied)")
        for item in self.occupancy:
            if not (isinstance(item, tuple) and len(item) == 2):
                raise ValueError(f"occupancy holds ((nx, ny, nz), occupied) pairs, got {item!r}")
            _check_grid_cells(*item)
        if self.changes and self.resolution is None:
            raise ValueError("changes need the sample's grid (resolution and occupied)")
        for item in self.changes:
            if not (isinstance(item, tuple) and len(item) == 2):
                raise ValueError(f"changes holds ((nx, ny, nz), changes per ray) pairs, got {item!r}")
            res, per_ray = item
            _check_grid_cells(res, 0)
            if isinstance(per_ray, bool) or not (isinstance(per_ray, (int, float)) and math.isfinite(per_ray)
                                                 and per_ray >= 0):
                raise ValueError(f"changes per ray must be a finite number >= 0, got {per_ray!r}")


def _check_grid_cells(res, occ):
    """A grid's resolution (three whole numbers >= 1) and its occupied cells (0 to all of them)."""
    if not (isinstance(res, tuple) and len(res) == 3
            and all(isinstance(x, int) and not isinstance(x, bool) and x >= 1 for x in res)):
        raise ValueError(f"resolution must be three whole numbers >= 1, got {res!r}")
    if isinstance(occ, bool) or not (isinstance(occ, int) and 0 <= occ <= res[0] * res[1] * res[2]):
        raise ValueError(f"occupied must be a whole number of the grid's cells, got {occ!r}")


@dataclass(frozen=True, eq=False)
class TriangleSample:
    """An evenly strided sample of a mesh's triangles, each standing for ``weight`` of them: what
    :func:`models.memory.read_bytes` weighs a grid's references by (where rays read them).

    extents : (k, 3) bounding-box extents; proj_areas : (k, 3) areas projected along each
    axis, ``A |n_i|``; areas : (k,) areas ``A``; weight : triangles per sampled one (>= 1).
    """

    extents: np.ndarray
    proj_areas: np.ndarray
    areas: np.ndarray
    weight: float

    def __post_init__(self):
        e = np.asarray(self.extents, dtype=np.float64)
        p = np.asarray(self.proj_areas, dtype=np.float64)
        if e.ndim != 2 or e.shape[1] != 3 or p.shape != e.shape or e.shape[0] < 1:
            raise ValueError(f"extents and proj_areas must both be (k, 3) with k >= 1, got {e.shape} and {p.shape}")
        a = np.asarray(self.areas, dtype=np.float64)
        if a.shape != (e.shape[0],):
            raise ValueError(f"areas must be ({e.shape[0]},), got {a.shape}")
        if not all(np.all(np.isfinite(x)) and np.all(x >= 0) for x in (e, p, a)):
            raise ValueError("extents, proj_areas and areas must be finite and >= 0")
        if not (math.isfinite(self.weight) and self.weight >= 1.0):
            raise ValueError(f"weight must be a finite number >= 1, got {self.weight!r}")


#: Triangles in a :class:`TriangleSample` (:func:`triangle_sample`).
TRIANGLE_SAMPLE_SIZE = 4096


def triangle_sample(vertices, faces, size: int = TRIANGLE_SAMPLE_SIZE) -> TriangleSample:
    """Every ``ceil(F / size)``-th triangle's extents and projected areas (:class:`TriangleSample`)."""
    v, f = _check_mesh(vertices, faces)
    stride = max(1, -(-f.shape[0] // int(size)))
    geom = triangle_geometry(v, f[::stride])
    return TriangleSample(extents=geom.ext, proj_areas=geom.proj_area, areas=geom.area,
                          weight=f.shape[0] / geom.area.shape[0])


@dataclass(frozen=True)
class SceneStats:
    """Scene statistics (scene units; counts are plain numbers).

    Attributes
    ----------
    n_triangles : int, N.
    box_lo, box_hi : (3,) float64, the grid box (:func:`grid_box` of the mesh bounds).
    extent : (3,) float64, ``box_hi - box_lo`` (all > 0).
    volume, surface : float, V and S of the grid box (units^3, units^2).
    e1, e1_axes : float and (3,): ``sum |ext|_1`` and its per-axis parts (units).
    e2, e2_axes : float and (3,): ``sum A |n|_1`` and projected-area sums (units^2).
    perimeters : (3,) float64, ``P_x, P_y, P_z`` projected perimeter sums (units).
    bbox_pair_sums : (3,) ``[sum ext_y ext_z, sum ext_z ext_x, sum ext_x ext_y]`` (units^2).
    bbox_triple_sum : float, ``sum ext_x ext_y ext_z`` (units^3).
    area : float, total triangle area (units^2).
    k : float, the talk's manifold constant ``E2 / V^(2/3)`` (6 for a cube's surface).
    aspect_median, aspect_p95 : float, AR = longest_edge^2 / (2 area) over
        non-degenerate triangles (``inf`` when all are degenerate); estimated from a
        strided sample of ``AR_SAMPLE_TRIANGLES`` when the mesh is larger.
    n_degenerate : int, triangles with AR > 1/DEGENERATE_REL_AREA or zero size.
    watertight : bool, see :func:`is_watertight`.
    enclosed_volume : float, see :func:`enclosed_volume`; 0.0 unless watertight.
    positions : int, distinct vertex positions (:func:`mesh_topology`), or 0 when not
        computed; see :attr:`separate_fraction`.
    termination : :class:`TerminationSample` or None, where rays traced through the
        real mesh stop (measured by the caller, which can trace: ``calibrate.predict``);
        None leaves :func:`models.effects.termination_fraction` to its approximation.
    triangles : :class:`TriangleSample` or None, what :func:`models.memory.read_bytes` weighs
        the references by; None charges the memory term on the whole grid.
    """

    n_triangles: int
    box_lo: np.ndarray
    box_hi: np.ndarray
    extent: np.ndarray
    volume: float
    surface: float
    e1: float
    e1_axes: np.ndarray
    e2: float
    e2_axes: np.ndarray
    perimeters: np.ndarray
    bbox_pair_sums: np.ndarray
    bbox_triple_sum: float
    area: float
    k: float
    aspect_median: float
    aspect_p95: float
    n_degenerate: int
    watertight: bool
    enclosed_volume: float
    positions: int = 0
    termination: TerminationSample | None = None
    triangles: TriangleSample | None = None

    @property
    def separate_fraction(self) -> float:
        """How far the triangles are from sharing their corners, in [0, 1].

        ``(P - N/2) / (5N/2)`` clipped, P distinct vertex positions: 0 for a closed
        triangulated surface (about N/2 positions, each shared by six triangles), 1 for
        triangles that share no corner (3N positions).  0 when P was not computed (a
        connected surface is assumed).  The occupied-cell model (models/general.py)
        uses it to decide how much of each triangle's cells its neighbours share.
        """
        n = float(self.n_triangles)
        if self.positions <= 0 or n <= 0:
            return 0.0
        return min(1.0, max(0.0, (self.positions - 0.5 * n) / (2.5 * n)))


def box_volume_surface(extent) -> tuple[float, float]:
    """(V, S) of a box with extents (3,) (units^3, units^2)."""
    d = [float(x) for x in np.asarray(extent, dtype=np.float64).reshape(3)]  # Python floats: inf, no warning
    return d[0] * d[1] * d[2], 2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0])


def stats_from_geometry(geom: TriangleGeometry, box_lo, box_hi, *, watertight: bool = False,
                        enclosed: float = 0.0) -> SceneStats:
    """SceneStats from per-triangle geometry and a grid box (no mesh topology needed)."""
    lo, hi = grid_box(box_lo, box_hi)
    extent = hi - lo
    volume, surface = box_volume_surface(extent)
    ext = geom.ext
    e1_axes = ext.sum(axis=0)
    e2_axes = geom.proj_area.sum(axis=0)
    pair = np.stack([ext[:, 1] * ext[:, 2], ext[:, 2] * ext[:, 0], ext[:, 0] * ext[:, 1]], axis=1)
    good = ~geom.degenerate
    if good.any():
        ar = geom.longest_edge_sq[good] / (2.0 * geom.area[good])
        ar_med, ar_p95 = (float(x) for x in np.percentile(ar, [50.0, 95.0]))
    else:
        ar_med = ar_p95 = float("inf")
    e2 = float(e2_axes.sum())
    return SceneStats(
        n_triangles=int(geom.area.shape[0]), box_lo=lo, box_hi=hi, extent=extent,
        volume=volume, surface=surface, e1=float(e1_axes.sum()), e1_axes=e1_axes,
        e2=e2, e2_axes=e2_axes, perimeters=geom.proj_perimeter.sum(axis=0),
        bbox_pair_sums=pair.sum(axis=0), bbox_triple_sum=float(np.prod(ext, axis=1).sum()),
        area=float(geom.area.sum()), k=e2 / volume ** (2.0 / 3.0),
        aspect_median=ar_med, aspect_p95=ar_p95, n_degenerate=int(geom.degenerate.sum()),
        watertight=bool(watertight), enclosed_volume=float(enclosed) if watertight else 0.0)


def enclosed_volume(vertices, faces) -> float:
    """|signed volume| of a closed, consistently oriented mesh (divergence theorem), units^3.

    Meaningful only for watertight, consistently oriented meshes; the caller decides.
    Corners are taken relative to the bounding-box centre to limit cancellation.
    """
    v, f = _check_mesh(vertices, faces)
    c = 0.5 * (v.min(axis=0) + v.max(axis=0))
    p = v[f] - c
    return float(abs(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum()) / 6.0)


def scene_stats(vertices, faces, *, topology=True) -> SceneStats:
    """Statistics of a triangle mesh for the cost models (one chunked pass over triangles).

    Parameters
    ----------
    vertices : (V, 3) float64, scene units. Must be finite.
    faces : (F, 3) int64, F >= 1.
    topology : also decide watertightness (an edge sort, about half the time on big
        meshes), count distinct vertex positions and, when watertight, find the
        enclosed volume.  False leaves ``watertight=False``, ``positions=0`` and
        ``enclosed_volume=0.0`` (treated as an open, connected mesh).

    Returns
    -------
    SceneStats (frozen).  The box is the grid box of the bounds of the referenced
    vertices.  Raises ``ValueError`` on malformed input.
    """
    v, f = _check_mesh(vertices, faces)
    n = f.shape[0]
    v3, corners = _columns(v, f)
    centre = 0.5 * (v3.min(axis=1) + v3.max(axis=1))  # reference point for the volume only
    box_lo = np.full(3, np.inf)
    box_hi = np.full(3, -np.inf)  # bounds of the triangles (unreferenced vertices ignored)
    e1 = np.zeros(3)
    e2 = np.zeros(3)
    per = np.zeros(3)
    pair = np.zeros(3)
    triple = area_sum = vol6 = 0.0
    n_good = 0
    for a in range(0, n, CHUNK_TRIANGLES):
        b = min(n, a + CHUNK_TRIANGLES)
        lo, hi, cross, pp, area, lsq, p0 = _chunk_geometry(v3, corners, a, b)
        ext = hi - lo
        box_lo = np.minimum(box_lo, lo.min(axis=1))
        box_hi = np.maximum(box_hi, hi.max(axis=1))
        e1 += ext.sum(axis=1)
        e2 += 0.5 * np.abs(cross).sum(axis=1)
        per += pp.sum(axis=1)
        rolled = ext[[1, 2, 0]]  # (y, z, x): pairs (x y, y z, z x) -> reorder to (yz, zx, xy)
        pair += (ext * rolled).sum(axis=1)[[1, 2, 0]]
        triple += float(np.einsum("j,j,j->", ext[0], ext[1], ext[2]))
        area_sum += float(area.sum())
        if topology:  # 6 x signed volume, corners relative to the centre c: (p0-c).(u x w)
            vol6 += float(np.einsum("ij,ij->", p0 - centre[:, None], cross))
        n_good += int(np.count_nonzero(2.0 * area > DEGENERATE_REL_AREA * lsq))
    watertight, positions = mesh_topology(v, f) if topology else (False, 0)
    stride = aspect_sample_stride(n)
    sample = [c[::stride] for c in corners] if stride > 1 else corners
    _, _, _, _, area, lsq, _ = _chunk_geometry(v3, sample, 0, sample[0].shape[0])
    good = 2.0 * area > DEGENERATE_REL_AREA * lsq
    return stats_from_sums(
        n_triangles=n, box_lo=box_lo, box_hi=box_hi, e1_axes=e1, e2_axes=e2, perimeters=per, pair_sums=pair,
        triple=triple, area=area_sum, vol6=vol6, n_good=n_good, aspect_sample=lsq[good] / (2.0 * area[good]),
        watertight=watertight, positions=positions)


def aspect_sample_stride(n_triangles: int) -> int:
    """Stride of the triangles whose aspect ratios estimate the percentiles (1: all of them)."""
    return max(1, int(n_triangles) // AR_SAMPLE_TRIANGLES)


def stats_from_sums(*, n_triangles, box_lo, box_hi, e1_axes, e2_axes, perimeters, pair_sums, triple, area, vol6,
                    n_good, aspect_sample, watertight, positions=0) -> SceneStats:
    """SceneStats from the sums of one pass over the triangles (see :func:`scene_stats`).

    ``box_lo``/``box_hi`` are the triangles' bounds (the grid box is derived here),
    ``vol6`` six times the signed enclosed volume, ``aspect_sample`` the aspect ratios
    of the non-degenerate triangles among every :func:`aspect_sample_stride`-th one.
    A fast implementation of the pass (e.g. compiled) hands its sums to this function,
    so both share every rule that turns sums into statistics.
    """
    ar = np.asarray(aspect_sample, dtype=np.float64)
    if ar.size:
        ar_med, ar_p95 = (float(x) for x in np.percentile(ar, [50.0, 95.0]))
    else:
        ar_med = ar_p95 = float("inf")
    tri_extent = np.asarray(box_hi, dtype=np.float64) - np.asarray(box_lo, dtype=np.float64)
    if not float(tri_extent.max()) > 0.0:
        raise ValueError("the scene has zero extent: every triangle lies at one point, so there is "
                         "no space for a grid to divide")
    lo_b, hi_b = grid_box(box_lo, box_hi)
    extent = hi_b - lo_b
    volume, surface = box_volume_surface(extent)
    if not (MIN_NORMAL_VOLUME <= volume < math.inf and surface < math.inf):
        which = "small" if volume < MIN_NORMAL_VOLUME else "large"
        raise ValueError(f"the scene is too {which} for its statistics in double precision (extent "
                         f"{float(extent.max()):.3g}: its box volume {'underflows' if which == 'small' else 'overflows'}); "
                         f"scale the mesh to an extent between {MIN_STATS_EXTENT:g} and {MAX_STATS_EXTENT:g}")
    e1 = np.asarray(e1_axes, dtype=np.float64)
    e2 = np.asarray(e2_axes, dtype=np.float64)
    e2_total = float(e2.sum())
    return SceneStats(
        n_triangles=int(n_triangles), box_lo=lo_b, box_hi=hi_b, extent=extent, volume=volume, surface=surface,
        e1=float(e1.sum()), e1_axes=e1, e2=e2_total, e2_axes=e2,
        perimeters=np.asarray(perimeters, dtype=np.float64), bbox_pair_sums=np.asarray(pair_sums, dtype=np.float64),
        bbox_triple_sum=float(triple), area=float(area), k=e2_total / volume ** (2.0 / 3.0),
        aspect_median=ar_med, aspect_p95=ar_p95, n_degenerate=int(n_triangles) - int(n_good),
        watertight=bool(watertight), enclosed_volume=abs(float(vol6)) / 6.0 if watertight else 0.0,
        positions=int(positions))


def scene_class(stats: SceneStats) -> tuple[str, str]:
    """The talk's scene class for the paper fidelity: ``("compact"|"long-skinny"|"mixed", reason)``.

    Rule (from the aspect-ratio distribution, AR = longest_edge^2 / (2 area)):
    - more than ``DEGENERATE_FRACTION_SKINNY`` of the triangles degenerate -> long-skinny;
    - median AR <= ``AR_COMPACT_MEDIAN_MAX`` and p95 <= ``AR_COMPACT_P95_MAX`` -> compact
      (triangles behave as the talk's points);
    - median AR >= ``AR_SKINNY_MEDIAN_MIN`` -> long-skinny (the talk's lines);
    - otherwise mixed.
    """
    n = stats.n_triangles
    frac_deg = stats.n_degenerate / n
    med, p95 = stats.aspect_median, stats.aspect_p95
    if frac_deg > DEGENERATE_FRACTION_SKINNY:
        return "long-skinny", (f"{100 * frac_deg:.0f}% of triangles degenerate "
                               f"(> {100 * DEGENERATE_FRACTION_SKINNY:.0f}%): segments")
    if med <= AR_COMPACT_MEDIAN_MAX and p95 <= AR_COMPACT_P95_MAX:
        return "compact", (f"aspect median {med:.3g} <= {AR_COMPACT_MEDIAN_MAX:g} and "
                           f"p95 {p95:.3g} <= {AR_COMPACT_P95_MAX:g}")
    if med >= AR_SKINNY_MEDIAN_MIN:
        return "long-skinny", f"aspect median {med:.3g} >= {AR_SKINNY_MEDIAN_MIN:g}"
    return "mixed", (f"aspect median {med:.3g}, p95 {p95:.3g}: between compact "
                     f"(<= {AR_COMPACT_MEDIAN_MAX:g}/{AR_COMPACT_P95_MAX:g}) and "
                     f"long-skinny (>= {AR_SKINNY_MEDIAN_MIN:g})")
