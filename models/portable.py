"""Portable resolution arithmetic: the grid resolutions that the exported C header reproduces bit for bit.

Every function here is scalar Python on IEEE double with only ``+ - * /``, ``sqrt``,
``floor``, ``frexp``, ``ldexp`` and ``nextafter`` (all exact or correctly rounded in
IEEE 754 and C99), each operation written in the order the C header
(``calibrate export``) writes it.  The logarithm, exponential and powers are our
own polynomials (:func:`plog`, :func:`pexp`, :func:`ppow`, about 1e-15 relative
error) rather than a libm's or numpy's, whose last bits differ between platforms and
between numpy's SIMD paths and the C library.  So a C program compiled without
fused multiply-add contraction (``-ffp-contract=off``, as the project builds its
kernels; no ``-ffast-math``) and the Python predictions return the same integers.

The functions mirror, operation for operation, ``static inline`` functions of the
generated header (``calibrate/export.py`` holds their C text):

========================================  =====================================
Python                                    C (``grid_tuning.h``)
========================================  =====================================
:func:`grid_extent`                       ``gridcal_grid_extent``
:func:`resolution_for_cells`              ``gridcal_resolution_for_cells``
:func:`paper_level_cells`                 ``gridcal_paper_level_cells``
:func:`paper_resolutions`                 ``gridcal_paper_level`` and the per-class wrappers
:func:`general_cells`                     ``gridcal_general_cells``
:func:`general_resolution`                ``gridcal_general_resolution``
:func:`scene_class_code`                  ``gridcal_scene_class``
========================================  =====================================

:func:`models.closed_forms.cells_to_resolution` and the paper fidelity of
``calibrate predict`` use these functions, so the header's resolutions are the
predictions' resolutions.  Bad inputs raise ``ValueError`` here; the C functions
return -1 (and write ``1 1 1``) for the same inputs.
"""

from __future__ import annotations

import math

from .stats import (AR_COMPACT_MEDIAN_MAX, AR_COMPACT_P95_MAX, AR_SKINNY_MEDIAN_MIN, DEGENERATE_FRACTION_SKINNY,
                    MIN_ABSOLUTE_EXTENT, MIN_EXTENT_FRACTION, POINT_SCENE_EXTENT_FRACTION)

# ln 2 split so that k * LN2_HI is exact for |k| < 2^20 (fdlibm's split).
LN2_HI = 6.93147180369123816490e-01
LN2_LO = 1.90821492927058770002e-10
INV_LN2 = 1.44269504088896338700e+00
SQRT_HALF = 7.07106781186547524401e-01
#: exp overflows above ln(DBL_MAX) = 709.7827...; pexp returns inf from here on.
EXP_OVERFLOW = 709.78
#: exp underflows to 0 below ln(smallest subnormal) = -744.44...
EXP_UNDERFLOW = -745.2
#: Terms of the atanh series of :func:`plog` (|s| <= 0.1716: the last term is below 1e-17).
LOG_TERMS = 12
#: Terms of the Taylor series of :func:`pexp` (|r| <= ln2/2: the last term is below 1e-17).
EXP_TERMS = 14
#: Newton iterations of the scaled cubic (as :data:`models.general.CUBIC_NEWTON_ITERATIONS`).
CUBIC_NEWTON_ITERATIONS = 40
#: Defaults of :func:`resolution_for_cells` (the same as models.closed_forms').
MAX_CELLS_PER_AXIS = 4096
MAX_TOTAL_CELLS = 2 ** 26
#: Talk's manifold constant for a cube (models.closed_forms.K_CUBE); the paper plan's
#: fallback when a scene's k is not finite, and its lower bound.
K_CUBE = 6.0
K_MIN = 1e-3
#: Scene classes as the header numbers them.
SCENE_CLASSES = ("compact", "long-skinny", "mixed")
#: Deepest nested grid of the paper plan (models.nested.MAX_LEVELS).
MAX_LEVELS = 3


def plog(x: float) -> float:
    """Natural logarithm of x >= 0 (0 -> -inf, inf -> inf), about 1e-15 relative error.

    ``x = m 2^e`` with m in [sqrt(1/2), sqrt(2)); ``log m = 2 atanh(s)``,
    ``s = (m - 1) / (m + 1)``, summed as an odd series in Horner form.
    """
    if not x > 0.0:
        if x == 0.0:
            return -math.inf
        raise ValueError(f"plog of a negative number or NaN: {x!r}")
    if x == math.inf:
        return math.inf
    m, e = math.frexp(x)
    if m < SQRT_HALF:
        m = m * 2.0
        e = e - 1
    f = m - 1.0
    s = f / (2.0 + f)
    z = s * s
    p = 1.0 / (2.0 * LOG_TERMS + 1.0)
    for j in range(LOG_TERMS - 1, 0, -1):
        p = 1.0 / (2.0 * j + 1.0) + z * p
    hs = s + s
    de = float(e)
    return de * LN2_HI + (hs + (hs * (z * p) + de * LN2_LO))


def pexp(x: float) -> float:
    """e^x for any float x (inf above EXP_OVERFLOW, 0 below EXP_UNDERFLOW), about 1e-15 relative error.

    ``x = k ln2 + t``, |t| <= ln2/2; ``e^t`` by its Taylor series in Horner form; ``ldexp``.
    """
    if x != x:
        raise ValueError("pexp of NaN")
    if x > EXP_OVERFLOW:
        return math.inf
    if x < EXP_UNDERFLOW:
        return 0.0
    k = float(math.floor(x * INV_LN2 + 0.5))
    t = (x - k * LN2_HI) - k * LN2_LO
    p = 1.0
    for j in range(EXP_TERMS, 0, -1):
        p = 1.0 + (t / float(j)) * p
    return math.ldexp(p, int(k))


def ppow(x: float, y: float) -> float:
    """x^y for x >= 0 and finite y: ``pexp(y plog(x))``; ``0^y`` is 0 for y > 0, ``x^0`` is 1."""
    if y == 0.0:
        return 1.0
    if x == 0.0:
        if y > 0.0:
            return 0.0
        return math.inf
    return pexp(y * plog(x))


def round_half_even(x: float) -> float:
    """x rounded to the nearest integer, ties to even (x >= 0 and below 2^52); independent of rounding modes."""
    f = float(math.floor(x))
    d = x - f
    if d > 0.5:
        return f + 1.0
    if d < 0.5:
        return f
    return f + 1.0 if math.fmod(f, 2.0) != 0.0 else f


def _finite(name, x) -> float:
    x = float(x)
    if not math.isfinite(x):
        raise ValueError(f"{name} must be finite, got {x!r}")
    return x


def grid_extent(lo, hi) -> tuple[float, float, float]:
    """Extents of the grid box of a scene box: the scalar form of :func:`models.stats.grid_box`.

    lo, hi : 3 floats each (scene units), finite, ``lo <= hi``.
    Returns (3,) floats ``hi' - lo'`` of ``grid_box(lo, hi)``, all > 0 (equal bit for
    bit: numpy's elementwise operations are IEEE operations too).
    """
    lo = [_finite("box corner", v) for v in lo]
    hi = [_finite("box corner", v) for v in hi]
    if len(lo) != 3 or len(hi) != 3:
        raise ValueError("box corners must have 3 coordinates each")
    for i in range(3):
        if hi[i] < lo[i]:
            raise ValueError(f"box has hi < lo on axis {i}")
    ext = [hi[i] - lo[i] for i in range(3)]
    emax = max(max(ext[0], ext[1]), ext[2])
    if emax > 0.0:
        width = MIN_EXTENT_FRACTION * emax
    else:
        amax = 0.0
        for v in (lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]):
            amax = max(amax, abs(v))
        width = max(POINT_SCENE_EXTENT_FRACTION * amax, MIN_ABSOLUTE_EXTENT)
    out = []
    for i in range(3):
        a, b = lo[i], hi[i]
        if ext[i] < width:
            centre = 0.5 * a + 0.5 * b
            a = centre - 0.5 * width
            b = centre + 0.5 * width
        for _ in range(64):
            if b - a > 0.0:
                break
            a = math.nextafter(a, -math.inf)
            b = math.nextafter(b, math.inf)
        if not (math.isfinite(a) and math.isfinite(b)):
            raise ValueError("box is too close to the float64 limit to widen")
        out.append(b - a)
    return out[0], out[1], out[2]


def resolution_for_cells(total_cells, extent, max_per_axis=MAX_CELLS_PER_AXIS,
                         max_total=MAX_TOTAL_CELLS) -> tuple[int, int, int]:
    """Per-axis resolution with near-cubic cells for ``total_cells`` cells over a box of ``extent``.

    The talk's rule ``n_i = d_i cbrt(M / (d_x d_y d_z))`` in log space (no product
    overflows), rounded half to even, each clamped to ``[1, max_per_axis]``; a product
    above ``max_total`` shrinks the axes > 1 together by ``(max_total / product)^(1/k)``
    (floored, at most 8 times), then the largest axis (first on ties) by one until it fits.

    total_cells : float > 0 (inf is clamped).  extent : 3 finite floats > 0.
    Returns (nx, ny, nz) ints, ``1 <= n_i <= max_per_axis``, ``nx ny nz <= max_total``.
    """
    m = float(total_cells)
    if not m > 0.0:
        raise ValueError(f"total_cells must be > 0, got {total_cells!r}")
    d = [float(v) for v in extent]
    if len(d) != 3 or not all(math.isfinite(v) and v > 0.0 for v in d):
        raise ValueError(f"extent must be 3 finite positive lengths, got {extent!r}")
    max_per_axis, max_total = int(max_per_axis), int(max_total)
    if max_per_axis < 1 or max_total < 1:
        raise ValueError("max_per_axis and max_total must be >= 1")
    log_m = min(plog(m), plog(float(max_total)) + 1.0)  # never needs more than max_total
    l0, l1, l2 = plog(d[0]), plog(d[1]), plog(d[2])
    third = (log_m - ((l0 + l1) + l2)) / 3.0
    cap = plog(float(max_per_axis)) + 1.0
    n = []
    for li in (l0, l1, l2):
        v = round_half_even(pexp(min(li + third, cap)))
        n.append(int(min(max(v, 1.0), float(max_per_axis))))
    for _ in range(8):
        prod = n[0] * n[1] * n[2]
        if prod <= max_total:
            break
        k = (n[0] > 1) + (n[1] > 1) + (n[2] > 1)
        q = float(max_total) / float(prod)
        shrink = q if k == 1 else (math.sqrt(q) if k == 2 else ppow(q, 1.0 / 3.0))
        n = [int(max(math.floor(float(v) * shrink), 1.0)) if v > 1 else v for v in n]
    while n[0] * n[1] * n[2] > max_total:  # at most a few steps
        i = 0 if (n[0] >= n[1] and n[0] >= n[2]) else (1 if n[1] >= n[2] else 2)
        n[i] -= 1
    return n[0], n[1], n[2]


def _positive(name, x) -> float:
    x = float(x)
    if not (math.isfinite(x) and x > 0.0):
        raise ValueError(f"{name} must be finite and > 0, got {x!r}")
    return x


def paper_k(k) -> float:
    """The manifold constant the paper plan uses: ``max(k, K_MIN)``, or K_CUBE when k is not finite."""
    k = float(k)
    return max(k, K_MIN) if math.isfinite(k) else K_CUBE


def paper_level_cells(n, r, levels, k=K_CUBE, kind="points") -> list[float]:
    """Cells ``m_l^3`` per level (top first) of the talk's optimal L-level grid: the scalar form of
    :func:`models.closed_forms.l_level_cells` (same recursion, same order of operations,
    portable powers; they agree to about 1e-14 relative).

    n : number of primitives > 0; r : T_int / T_step > 0; levels : 1..; k > 0 (the
    manifold constant); kind : "points" (compact) or "lines" (long skinny).
    """
    if kind not in ("points", "lines"):
        raise ValueError(f"kind must be 'points' or 'lines', got {kind!r}")
    if int(levels) != levels or levels < 1:
        raise ValueError(f"levels must be an integer >= 1, got {levels!r}")
    n, r, k = _positive("n", n), _positive("r", r), _positive("k", k)
    levels = int(levels)
    points = kind == "points"
    # (p, a) of the optimal cost a N^p of 1..L-level grids.
    if points:
        pa = [(1.0 / 3.0, 1.5 * ppow(2.0 * r, 1.0 / 3.0))]
    else:
        pa = [(0.5, 2.0 * math.sqrt(r))]
    for _ in range(1, levels):
        p, a = pa[-1]
        if points:
            c = ppow(2.0 * p * a * ppow(k, 1.0 - p), 1.0 / (2.0 * p + 1.0))
            pa.append((p / (2.0 * p + 1.0), (1.0 + 1.0 / (2.0 * p)) * c))
        else:
            c = ppow(p * a * ppow(k, 1.0 - p), 1.0 / (p + 1.0))
            pa.append((p / (p + 1.0), (1.0 + 1.0 / p) * c))
    cells = []
    n_level = n
    for depth in range(levels):
        remaining = levels - depth
        if remaining == 1:
            cells.append(2.0 * n_level * r if points else ppow(n_level * r, 1.5))
            break
        p, a = pa[remaining - 2]
        if points:
            m = ppow(2.0 * p * a * ppow(k, 1.0 - p) * ppow(n_level, p), 1.0 / (2.0 * p + 1.0))
            n_level = n_level / (k * m * m)
        else:
            m = ppow(p * a * ppow(k, 1.0 - p) * ppow(n_level, p), 1.0 / (p + 1.0))
            n_level = n_level / (k * m)
        cells.append(m * m * m)
    return cells


def paper_resolutions(n, lo, hi, r, levels=1, scene_class="compact", k=K_CUBE) -> list[tuple[int, int, int]]:
    """Per-level resolutions (top first) of the talk's closed forms for a scene box: the grid of
    ``calibrate predict --fidelity paper --levels L`` (:func:`calibrate.predict.paper_plan`).

    n : primitives (``n < 1``, an empty scene, gives one cell per level);
    lo, hi : the scene's bounding box (3 floats each), widened by :func:`grid_extent`;
    r : T_int / T_step > 0; levels : 1..MAX_LEVELS;
    scene_class : "compact" or "mixed" (the points law) or "long-skinny" (the lines law);
    k : the scene's ``E2 / V^(2/3)`` (6 for a cube), through :func:`paper_k`.

    Level 1 spreads :func:`paper_level_cells`' top count over the grid box; level l + 1
    spreads its count over one cell of level l (``extent / resolution``).
    """
    n = float(n)
    if n != n:
        raise ValueError("n must be a number, got NaN")
    ext = grid_extent(lo, hi)
    r = _positive("r", r)
    if int(levels) != levels or not 1 <= levels <= MAX_LEVELS:
        raise ValueError(f"levels must be 1..{MAX_LEVELS}, got {levels!r}")
    if scene_class not in SCENE_CLASSES:
        raise ValueError(f"scene_class must be one of {SCENE_CLASSES}, got {scene_class!r}")
    if n < 1.0:
        return [(1, 1, 1)] * int(levels)
    kind = "lines" if scene_class == "long-skinny" else "points"
    cells = paper_level_cells(n, r, int(levels), paper_k(k), kind=kind)
    out = []
    for c in cells:
        res = resolution_for_cells(c, ext)
        out.append(res)
        ext = (ext[0] / float(res[0]), ext[1] / float(res[1]), ext[2] / float(res[2]))
    return out


def general_cells(n, e1, extent, r) -> float:
    """Total cells ``V / h*^3`` of the general model's single-level optimum (cubic cells of side h*).

    h* is the positive root of ``2 N r h^3 + E1 r h^2 - V = 0`` (DESIGN §3.2: exact
    overlap, no mailbox, rays never terminate), found as
    :func:`models.general.solve_cell_cubic` finds it: scaled ``x = h / h_a``,
    ``h_a = (V / (2 N r))^(1/3)`` in log space, Newton from ``min(1, beta^(-1/2))``.
    The count is then ``2 N r / x^3``, so no volume is ever formed (boxes from 1e-100
    to 1e100 work).  n > 0 primitives, e1 >= 0 (sum of triangle bounding-box L1
    extents, scene units; 0 gives the talk's points law 2 N r), extent 3 floats > 0.
    """
    n, r = _positive("n", n), _positive("r", r)
    e1 = float(e1)
    if not (math.isfinite(e1) and e1 >= 0.0):
        raise ValueError(f"e1 must be finite and >= 0, got {e1!r}")
    a = 2.0 * n * r
    if a == math.inf:
        return math.inf
    b = r * e1
    log_c = (plog(extent[0]) + plog(extent[1])) + plog(extent[2])
    log_ha = (log_c - plog(a)) / 3.0
    beta = b * pexp(2.0 * log_ha - log_c)
    if not beta < math.inf:
        raise ValueError("e1 is too large for the box")
    x = min(1.0, 1.0 / math.sqrt(max(beta, 1e-300)))
    for _ in range(CUBIC_NEWTON_ITERATIONS):
        fx = x * x * (x + beta) - 1.0
        dfx = x * (3.0 * x + 2.0 * beta)
        x = x - fx / dfx
    return a / (x * x * x)


def general_resolution(n, e1, lo, hi, r) -> tuple[int, int, int]:
    """Resolution of the general model's single-level optimum for a scene box (:func:`general_cells`
    spread over :func:`grid_extent` by :func:`resolution_for_cells`).  ``n < 1`` gives (1, 1, 1).

    This is the continuous optimum that :func:`models.general.optimal_uniform` starts
    from; ``calibrate predict --fidelity analytic`` refines it with the mesh's area sums
    and termination, which a header function cannot know.
    """
    n = float(n)
    if n != n:
        raise ValueError("n must be a number, got NaN")
    ext = grid_extent(lo, hi)
    if n < 1.0:
        _positive("r", r)
        return 1, 1, 1
    return resolution_for_cells(general_cells(n, e1, ext, r), ext)


def scene_class_code(n_triangles, n_degenerate, aspect_median, aspect_p95) -> int:
    """:func:`models.stats.scene_class` as a number: 0 compact, 1 long-skinny, 2 mixed (SCENE_CLASSES).

    aspect_median, aspect_p95 : of AR = longest_edge^2 / (2 area) over non-degenerate
    triangles (inf when there are none).
    """
    n = float(n_triangles)
    if not n > 0.0:
        raise ValueError(f"n_triangles must be > 0, got {n_triangles!r}")
    if float(n_degenerate) / n > DEGENERATE_FRACTION_SKINNY:
        return 1
    if aspect_median <= AR_COMPACT_MEDIAN_MAX and aspect_p95 <= AR_COMPACT_P95_MAX:
        return 0
    if aspect_median >= AR_SKINNY_MEDIAN_MIN:
        return 1
    return 2
