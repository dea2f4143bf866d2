"""The memory effect: cache lines a ray fetches from beyond the cache.

The four-constant model prices a cell step and a triangle test the same in a
grid that fits the cache and in one that does not.  Measured, they differ: on
the 1,996-triangle cylinder at 23x23x117 cells (11.7 MB) the same rays take
about 120 ns each when a few of them are traced over and over (their cells and
triangles stay cached) and about 350 ns when 8,192 different rays are
(docs/calibration.md, "The memory effect").  Fitting four constants to
traversals of grids from 0.1 to 44 MB leaves a misfit of 10-13% that grows
with the grid's size.

The model here adds one term per ray, ``T_mem * lines``, where ``lines`` is the
expected number of cache lines a ray fetches from beyond the cache:

    lines = miss_fraction(F, C) * (steps * STEP_LINES + visits * VISIT_LINES + tests * TEST_LINES)

with ``visits`` what T_visit prices: the occupied cells a ray enters and its changes of
occupancy (:func:`models.general.occupancy_changes`).

- A step: ``STEP_LINES``, one line.  The kernels read a cell's bit in the grid's
  occupancy bitmap (one bit a cell) and its 8-byte record only where the bit is set
  (kernels/gc_internal.h), so an empty cell no longer fetches its record: a step through
  empty cells beyond the cache fell from 34-37 ns to 4-5 ns (docs/kernels.md, "The
  occupancy bitmap").  The line a step is charged stands for what fine grids still pay
  by the step: the bitmap's lines from the outer caches (a bitmap of 8 MiB at 67 million
  cells), the pages it spans.  Priced on the bitmap's own bytes instead
  (``miss_fraction(cells / 8, C)`` a step), the model fits the calibration's timings as
  well (held-back 2.5% against 2.2%, cross-validated 2.0% both; its grids reach 42 MiB,
  where no bitmap misses) but puts ``cylinder19996`` at 310x279x390 cells, priced 717 ns
  a ray at 336x336x593 where 1,420 were measured; the line a step keeps the plan on the
  flat cells measured fastest (175x134x3, 347 ns).  A quarter line a step (with the
  visits' lines below and half a line a test) fits the suite's timings better still
  (2026-12-07: 14-15 log units over a line a step and none a visit, against 5-6 for the
  weights here) but plans ``cylinder19996`` at 111x111x178 from one of two calibrations
  of an hour, 2.5 times slower than the flat 185x143x2 another plan of that hour measured:
  the suite's grids end at 42 MiB, and what a step costs in a grid of 200 MB it cannot say.
- An occupied cell entered: ``VISIT_LINES``, two lines, its record and the first line of
  its references' packs, each at a place in memory set by the cell alone.  Nothing was
  charged for it until 2026-12-07; with it the suite's timings fit better by 5-6 log units
  (calibrate.run.select_cache's score, two default runs refitted) and Sponza, whose rays
  enter one or two cells of a big grid, is planned within 2% of its measured best (10%
  without; docs/calibration.md, "Two lines for an occupied cell").
- A test reads one reference's copy of its triangle (72 bytes of coordinates,
  stored with the reference in a pack of four; the 4-byte face index beside
  them is read only on a hit): ``TEST_LINES = 72 / 64`` lines.
- ``miss_fraction(F, C)``: the share of a grid of F bytes that the cache cannot
  hold, i.e. the chance that a line touched at random is not cached.  For one
  cache of C bytes it is ``max(0, 1 - C / F)``, 0 while the grid fits.  The
  cache a traversal runs out of is not one size, so C is the middle of a
  spread of capacities (a normal law in log2 of the capacity, one octave wide:
  CACHE_SPREAD_OCTAVES) and the share is the mean of ``max(0, 1 - C' / F)``
  over it.  One hard C put a cliff in the cost at C: a grid 15% over an 8 MiB
  cache paid 13% of its lines, and the plan searched around the armadillo's
  9 MiB optimum jumped to 15x17x13 under the cliff (+28-37% on measured sweeps); the
  calibrations kept a different C from run to run (8 or 16 MiB, whose fits
  differ by 50% in r), and the spread fits every run's timings better
  (docs/calibration.md, "A spread of cache sizes").

C is the cache the traversal runs out of.  Which level that is depends on the
host: on a Xeon whose level-3 share is small the level-2 cache (1-2 MiB); on a
2-core EPYC virtual machine (1 MiB L2, 32 MiB L3) a dependent load costs 5 ns
within 256 KiB, 17-35 ns from 2 to 12 MiB and 53-158 ns from 16 MiB on, and
the in-context timings fit best with C = 8-16 MiB.  ``calibrate run`` therefore
tries the sizes :func:`candidate_cache_sizes` gives between the host's level-2
and last-level caches (read from the operating system) and keeps the one whose
fit of the timings is best, stored with the calibration.  T_mem is fitted with
the other constants.  Pure math: no clocks, no kernels.
"""

from __future__ import annotations

import functools

import numpy as np

__all__ = ["LINE_BYTES", "STEP_LINES", "VISIT_LINES", "TEST_LINES", "BITMAP_BYTES_PER_CELL", "miss_fraction",
           "lines_beyond_cache", "line_weights", "candidate_cache_sizes", "weighted_miss_fraction", "read_bytes",
           "READ_RATE_BINS"]

#: Bytes of a cache line.
LINE_BYTES = 64
#: Lines a cell step is charged (see the module's notes: the bitmap's line and the pages fine
#: grids span, as measured, rather than the bit alone).
STEP_LINES = 1.0
#: Lines an occupied cell entered (or a change of occupancy, as T_visit counts them) is
#: charged: the cell's record and the first line of its packs.
VISIT_LINES = 2.0
#: Bytes of the occupancy bitmap a cell takes (a bit).
BITMAP_BYTES_PER_CELL = 1.0 / 8.0
#: Lines a triangle test reads (the reference's 72-byte copy of its triangle).
TEST_LINES = 72.0 / LINE_BYTES


def line_weights() -> dict:
    """The lines a step, an occupied cell entered and a test are charged, as a calibration records
    them (``meta.line_weights``): a T_mem is fitted for these weights and no others."""
    return {"step": STEP_LINES, "visit": VISIT_LINES, "test": TEST_LINES}


#: The cache a traversal runs out of is not one size: the level-2 cache, the level-3 share
#: the neighbours leave, the lines the prefetchers bring.  ``cache_bytes`` C is the middle of
#: a spread of capacities C 2^(j/2), j = -CACHE_SPREAD_STEPS .. CACHE_SPREAD_STEPS, weighted
#: as a normal law in log2 of the capacity with CACHE_SPREAD_OCTAVES standard deviation, and
#: a share of bytes misses as the weighted mean of what each capacity misses.  One hard
#: capacity (the spread 0) puts a cliff at C: a grid a little over C pays a tenth of its
#: lines, one a little under nothing, and a plan searched near C escapes under it.
CACHE_SPREAD_OCTAVES = 1.0
CACHE_SPREAD_STEPS = 6


def _capacities(cache_bytes):
    """((weight, capacity), ...) of the spread around ``cache_bytes`` (weights sum to 1), smallest
    capacity first."""
    return _spread(float(cache_bytes), float(CACHE_SPREAD_OCTAVES), int(CACHE_SPREAD_STEPS))


@functools.lru_cache(maxsize=64)
def _spread(c, octaves, steps):
    if octaves <= 0:
        return ((1.0, c),)
    j = np.arange(-steps, steps + 1, dtype=np.float64)
    w = np.exp(-0.5 * (0.5 * j / octaves) ** 2)
    w /= w.sum()
    return tuple((float(wj), c * 2.0 ** (0.5 * jj)) for wj, jj in zip(w, j))


def miss_fraction(memory_bytes, cache_bytes):
    """The mean of max(0, 1 - C' / memory_bytes) over the capacities C' of the spread around
    ``cache_bytes`` (:data:`CACHE_SPREAD_OCTAVES`), elementwise; 0 for an empty grid or no cache
    size, 0 below the spread's smallest capacity, rising continuously to 1 (a kink at each
    capacity, the largest a fifth of one capacity's).

    memory_bytes : grid bytes (>= 0, array-like); cache_bytes : bytes of the cache (> 0) or None.
    """
    f = np.asarray(memory_bytes, dtype=np.float64)
    if cache_bytes is None:
        return np.zeros_like(f)
    c = float(cache_bytes)
    if not (np.isfinite(c) and c > 0):
        raise ValueError(f"cache_bytes must be a finite number > 0, got {cache_bytes!r}")
    if np.any(~np.isfinite(f)) or np.any(f < 0):
        raise ValueError("memory_bytes must be finite and >= 0")
    caps = _capacities(c)
    if f.ndim == 0:  # the planner's many single grids: no arrays
        x = float(f)
        return np.float64(sum(w * (1.0 - cj / x) for w, cj in caps if x > cj))
    out = np.zeros_like(f)
    safe = np.where(f > 0, f, 1.0)
    for w, cj in caps:
        out += w * np.where(f > cj, 1.0 - cj / safe, 0.0)
    return out


def weighted_miss_fraction(rates, sizes, cache_bytes) -> float:
    """The share of the bytes read that miss a cache of ``cache_bytes`` (the mean over the spread
    of capacities around it, as :func:`miss_fraction`), when item ``i`` (a cell's
    record and reference list) of ``sizes[i]`` bytes is read whole at ``rates[i]`` reads per ray
    (Che's approximation of a least-recently-used cache under independent reads).

    The cache keeps an item read within the last ``T`` rays, ``T`` the characteristic time
    that fills it: ``sum_i sizes_i (1 - exp(-rates_i T)) = C``; a read misses when the
    item's last read is older, ``exp(-rates_i T)``, so the share of bytes that miss is

        ``sum_i rates_i sizes_i exp(-rates_i T) / sum_i rates_i sizes_i``.

    With every item read at the same rate (isotropic lines that never stop enter every
    cell of a uniform grid alike: Crofton) it is :func:`miss_fraction` of the bytes read,
    ``1 - C / F``; where rates differ, the bytes read often stay cached and the share is
    lower.  0 when the items read fit the cache or nothing is read.  Pure math: the rates
    are the caller's (``calibrate.reach`` counts them on a grid and a batch of rays).

    rates : (n,) reads per ray, >= 0.  sizes : (n,) bytes, >= 0.  cache_bytes : > 0.
    """
    lam = np.asarray(rates, dtype=np.float64).ravel()
    b = np.asarray(sizes, dtype=np.float64).ravel()
    if lam.shape != b.shape:
        raise ValueError(f"rates and sizes must have the same length, got {lam.size} and {b.size}")
    if not (np.all(np.isfinite(lam)) and np.all(lam >= 0) and np.all(np.isfinite(b)) and np.all(b >= 0)):
        raise ValueError("rates and sizes must be finite and >= 0")
    c0 = float(cache_bytes)
    if not (np.isfinite(c0) and c0 > 0):
        raise ValueError(f"cache_bytes must be a finite number > 0, got {cache_bytes!r}")
    read = lam > 0
    lam, b = lam[read], b[read]
    traffic = float(np.sum(lam * b))
    if traffic <= 0.0:
        return 0.0
    caps = _capacities(c0)
    total = float(b.sum())
    short = [(w, c) for w, c in caps if total > c]  # the capacities that cannot hold every item read
    if not short:
        return 0.0
    w = np.array([x[0] for x in short])
    c = np.array([x[1] for x in short])

    # held(t) = sum b (1 - exp(-lam t)) rises and is concave from held(0) = 0 to sum b > c: Newton's
    # steps from t = 0 stay below the root and approach it monotonically (quadratically near it);
    # one characteristic time per capacity, all solved at once
    t = np.zeros_like(c)
    for _ in range(200):
        e = np.exp(-np.outer(t, lam))
        gap = c - (1.0 - e) @ b
        going = gap > 1e-12 * c
        if not going.any():
            break
        t = np.where(going, t + gap / np.maximum(e @ (b * lam), np.finfo(np.float64).tiny), t)
    share = np.exp(-np.outer(t, lam)) @ (lam * b) / traffic
    return float(w @ share)


#: Bins (in the logarithm of the rate) the sampled triangles' read rates are pooled into
#: before :func:`weighted_miss_fraction` (pooled, its cost does not grow with the sample).
READ_RATE_BINS = 48


def read_bytes(triangles, extent, resolution, steps, tests, memory_bytes, cache_bytes,
               reference_bytes: float = 76.0, cell_bytes: float = BITMAP_BYTES_PER_CELL) -> float:
    """The grid bytes the memory term charges a uniform grid: ``memory_bytes`` where the grid fits
    the spread's smallest capacity or nothing says where rays read; beyond it, the size F' whose
    :func:`miss_fraction` is the share of the bytes read that misses
    (:func:`weighted_miss_fraction`) when each cell is read as often as rays stop in it.

    Rays stop at the surface, and a cell is entered in proportion to the surface it holds:
    isotropic lines meet a surface element in proportion to its area (Crofton), and a
    locally flat surface of normal n crosses a cell of sides c with area ``V_c / (|n| . c)``
    on average over its offsets (the cell's volume over its width along n).  So every copy
    of triangle t is read at a rate in proportion to ``1 / sum_i |n_t,i| c_i``, the
    triangle's ``m_t`` copies (``1 + sum_i ext_i / c_i + sum_i A|n_i| / (c_j c_k)``, as
    :func:`models.general.expected_refs` counts them) hold ``reference_bytes`` each, and
    the rates are scaled to the ``tests`` a ray makes; what a step reads of each cell
    (``cell_bytes``: its occupancy bit, an eighth of a byte) is read at ``steps`` over the
    cells.  On ``cylinder19996`` the end caps, fans of long
    chords across the disk, hold 85% of the references at 65x65x12 cells in cells with a
    36th of the wall's surface: priced this way the grids 12 cells long come out the
    cheapest, as measured, where the whole grid prices every shape alike
    (docs/calibration.md, "What rays read of a big grid").  APPROXIMATE: no occlusion (a
    surface behind another is read as often as an outer one) and no lines that pass
    through a cell without stopping in it.

    triangles : :class:`models.stats.TriangleSample` or None.  extent : (3,) the grid box's
    sides.  resolution : (3,) cells.  steps, tests : per ray (the model's).  memory_bytes,
    cache_bytes : the grid's bytes and the cache's (None: no memory term).
    """
    mem = float(memory_bytes)
    if triangles is None or cache_bytes is None or not tests > 0:
        return mem
    caps = _capacities(cache_bytes)
    smallest = caps[0][1]
    if not mem > smallest:  # fits the smallest capacity of the spread
        return mem
    ext = np.asarray(extent, dtype=np.float64)
    n = np.asarray(resolution, dtype=np.float64)
    c = ext / n
    cc = np.array([c[1] * c[2], c[2] * c[0], c[0] * c[1]])
    e, p = triangles.extents, triangles.proj_areas
    copies = triangles.weight * (1.0 + e @ (1.0 / c) + p @ (1.0 / cc))
    width = p @ c  # A (|n| . c): the triangle's area times the cell's width along its normal
    area = triangles.areas
    flat = (width > 0) & (area > 0)
    if not flat.any():
        return mem
    shape = np.zeros_like(width)
    shape[flat] = area[flat] / width[flat]  # 1 / (|n| . c), a copy's reads up to a common factor
    rate = tests * shape / float(np.sum(copies * shape))
    size = reference_bytes * copies
    read = rate > 0
    logs = np.log(rate[read])
    bins = np.minimum(((logs - logs.min()) / max(float(np.ptp(logs)), 1e-12) * READ_RATE_BINS).astype(np.int64),
                      READ_RATE_BINS - 1)
    pooled_size = np.bincount(bins, weights=size[read], minlength=READ_RATE_BINS)
    pooled_rate = np.bincount(bins, weights=(rate * size)[read], minlength=READ_RATE_BINS)
    keep = pooled_size > 0
    cells = float(np.prod(n))
    rates = np.concatenate([pooled_rate[keep] / pooled_size[keep], [max(float(steps), 0.0) / cells]])
    sizes = np.concatenate([pooled_size[keep], [cell_bytes * cells]])
    miss = weighted_miss_fraction(rates, sizes, cache_bytes)
    if not miss > 0.0:
        return min(mem, smallest)
    if not miss < float(miss_fraction(mem, cache_bytes)):
        return mem
    # the bytes F' whose miss_fraction is the share read that misses: between two capacities of
    # the spread, miss_fraction(F) = W - S / F (W, S: the weights and the weighted capacities
    # below F), which rises with F and is solved for F there
    acc_w = acc_s = 0.0
    for i, (w, c) in enumerate(caps):
        acc_w += w
        acc_s += w * c
        if i + 1 == len(caps) or miss < acc_w - acc_s / caps[i + 1][1]:
            return float(min(mem, acc_s / (acc_w - miss)))
    return mem


def lines_beyond_cache(steps, tests, memory_bytes, cache_bytes, visits=0.0):
    """Expected cache lines fetched from beyond the cache, for the given steps, tests and
    ``visits`` (the occupied cells entered and changes of occupancy, what T_visit prices).

    Works on per-ray values and on batch totals alike (it is linear in the counts).
    """
    s = np.asarray(steps, dtype=np.float64)
    t = np.asarray(tests, dtype=np.float64)
    v = np.asarray(visits, dtype=np.float64)
    return miss_fraction(memory_bytes, cache_bytes) * (STEP_LINES * s + VISIT_LINES * v + TEST_LINES * t)


def candidate_cache_sizes(smallest, largest) -> list[int]:
    """Cache sizes (bytes) to try for C: ``smallest``, each doubling of it below ``largest``,
    and ``largest``; ``[smallest]`` when ``largest`` is None or not above it.

    smallest : bytes of the level-2 cache (> 0); largest : bytes of the last-level cache, or None.
    """
    lo = int(smallest)
    if lo <= 0:
        raise ValueError(f"smallest must be > 0, got {smallest!r}")
    if largest is None or int(largest) <= lo:
        return [lo]
    hi = int(largest)
    out = [lo]
    while out[-1] * 2 < hi:
        out.append(out[-1] * 2)
    return out + [hi]
