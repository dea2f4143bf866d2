"""`calibrate export`: the host's constants and resolution rules as one C header.

:func:`header_text` turns a calibration (or a ratio ``r = T_int / T_step`` alone) into
``grid_tuning.h``: an include guard; each constant with its unit, median, 95%
interval and the calibration's provenance in a comment, each inside
``#ifndef NAME ... #endif`` so a user can override it; and ``static inline``
functions that turn (N, scene box, E1, scene class, level) into per-axis
resolutions.  The functions mirror :mod:`models.portable` operation by operation, so
they return exactly what the Python predictions return (tests/test_export.py
compiles the header and checks it).  :func:`add_parser` registers the verb.

Host text (CPU name, compiler flags, dates, paths) passes :func:`sanitize_comment`
before it enters a comment: printable ASCII only, no comment delimiters, no
backslash (no line splice), no ``??`` (no trigraph).
"""

from __future__ import annotations

import json
import math
import re
import sys
from pathlib import Path

from models import portable as P

from ._io import UserError, atomic_write_text

DEFAULT_HEADER = "grid_tuning.h"
DEFAULT_CALIBRATION = "calibration.json"
#: Longest host string kept in a comment (longer ones end in "...").
MAX_COMMENT_FIELD = 160
#: Fingerprint keys shown in the header's provenance, with their labels.
PROVENANCE_KEYS = (("cpu_model", "CPU"), ("logical_cores", "logical cores"), ("governor", "frequency governor"),
                   ("os", "OS"), ("kernel", "OS kernel"), ("date_utc", "date (UTC)"),
                   ("kernel_build", "kernels built with"), ("kernel_isa", "traversal's instruction set"))
#: Constants of a calibration, in header order: (key, macro, what, unit).
CONSTANTS = (("t_setup_ns", "GRIDCAL_T_SETUP_NS", "T_setup, cost of one ray's set-up", "ns per ray"),
             ("t_step_ns", "GRIDCAL_T_STEP_NS", "T_step, cost of one cell step", "ns per cell step"),
             ("t_int_ns", "GRIDCAL_T_INT_NS", "T_int, cost of one ray/triangle test", "ns per test"),
             ("t_sub_ns", "GRIDCAL_T_SUB_NS", "T_sub, cost of entering one subgrid", "ns per subgrid entered"),
             ("t_mem_ns", "GRIDCAL_T_MEM_NS", "T_mem, cost of one cache line fetched from beyond the cache "
              "(the memory effect, GRIDCAL_CACHE_BYTES below; `calibrate predict` adds it, the resolution "
              "functions of this header do not)", "ns per cache line"),
             ("t_visit_ns", "GRIDCAL_T_VISIT_NS", "T_visit, cost of entering one cell that holds triangles, and of "
              "each change of occupancy along a walk, beyond the step (`calibrate predict` adds it, the resolution "
              "functions of this header do not)",
              "ns per occupied cell entered or change of occupancy"),
             ("t_hit_ns", "GRIDCAL_T_HIT_NS", "T_hit, cost of a ray's hit beyond its tests (`calibrate predict` "
              "adds it for the share of rays that hit; the resolution functions of this header do not)",
              "ns per ray that hits"),
             ("ratio", "GRIDCAL_RATIO", "r = T_int / T_step, the ratio every resolution below uses",
              "dimensionless"))
#: The public functions of the header (``--json`` lists them).
FUNCTIONS = ("gridcal_compact", "gridcal_long_skinny", "gridcal_mixed", "gridcal_nested", "gridcal_general",
             "gridcal_paper_resolution", "gridcal_general_resolution_r", "gridcal_scene_class",
             "gridcal_grid_extent", "gridcal_resolution_for_cells", "gridcal_paper_level_cells",
             "gridcal_general_cells")

_TRIGRAPH_OR_DELIMITER = re.compile(r"\*/|/\*|\?\?")


def sanitize_comment(value, max_len: int = MAX_COMMENT_FIELD) -> str:
    """Text safe inside a C block comment on one line.

    Anything not printable ASCII (line breaks, tabs, control and non-ASCII characters)
    becomes ``_``; a backslash becomes ``/`` (no line splice); ``*/``, ``/*`` and ``??``
    (a trigraph's start: ``??/`` is a backslash in C99) get a space inserted; the
    result is cut to ``max_len`` characters (ending in ``...``).  Non-strings are
    written as compact JSON first.
    """
    if not isinstance(value, str):
        try:
            value = json.dumps(value, separators=(",", ":"), ensure_ascii=True, sort_keys=True)
        except (TypeError, ValueError):
            value = repr(value)
    text = "".join(c if " " <= c <= "~" else "_" for c in value).replace("\\", "/")
    if len(text) > max_len:
        text = text[:max(0, max_len - 3)] + "..."
    while _TRIGRAPH_OR_DELIMITER.search(text):
        text = _TRIGRAPH_OR_DELIMITER.sub(lambda m: m.group(0)[0] + " " + m.group(0)[1], text)
    return text.strip() or "(empty)"


def _c_double(x: float) -> str:
    """A C double literal that parses to exactly x (shortest round-trip repr)."""
    x = float(x)
    if not math.isfinite(x):
        raise ValueError(f"cannot write {x!r} as a C constant")
    text = repr(x)
    return text if ("." in text or "e" in text) else text + ".0"


def _fmt(x) -> str:
    return f"{float(x):.6g}"


# ---------------------------------------------------------------------------------------
# the functions (C text mirroring models.portable, operation by operation)
# ---------------------------------------------------------------------------------------

def _c_functions() -> str:
    d = _c_double
    return f"""
/* ---- scene classes (models.stats.scene_class) ------------------------------------- */
#define GRIDCAL_COMPACT 0     /* compact triangles: the talk's points, M = 2 N r */
#define GRIDCAL_LONG_SKINNY 1 /* long skinny triangles: the talk's lines, M = (N r)^1.5 */
#define GRIDCAL_MIXED 2       /* neither: the points law, as calibrate predict uses */
#define GRIDCAL_MAX_LEVELS {P.MAX_LEVELS}  /* deepest nested grid */

/* ---- clamps (models.closed_forms): cells per axis and cells per (sub)grid -----------
 * Overriding these departs from gridcal's predictions, which use these values. */
#ifndef GRIDCAL_MAX_CELLS_PER_AXIS
#define GRIDCAL_MAX_CELLS_PER_AXIS {P.MAX_CELLS_PER_AXIS}
#endif
#ifndef GRIDCAL_MAX_TOTAL_CELLS
#define GRIDCAL_MAX_TOTAL_CELLS {P.MAX_TOTAL_CELLS}
#endif
#if GRIDCAL_MAX_CELLS_PER_AXIS < 1 || GRIDCAL_MAX_CELLS_PER_AXIS > 1048576
#error "GRIDCAL_MAX_CELLS_PER_AXIS must be in [1, 2^20] (the product of three axes must fit 64 bits)"
#endif
#if GRIDCAL_MAX_TOTAL_CELLS < 1 || GRIDCAL_MAX_TOTAL_CELLS > 2147483647
#error "GRIDCAL_MAX_TOTAL_CELLS must be in [1, 2^31 - 1]"
#endif

/* ---- portable arithmetic (models.portable): + - * / and exact C99 functions only ----
 * (sqrt floor fmod fabs frexp ldexp nextafter).  Our own log/exp, so every platform gives
 * the same bits.  Build without -ffast-math and with -ffp-contract=off (no fused
 * multiply-add) for results identical to Python's. */

static inline int gridcal_finite_(double x) {{ return x == x && x != HUGE_VAL && x != -HUGE_VAL; }}
static inline int gridcal_positive_(double x) {{ return gridcal_finite_(x) && x > 0.0; }}
static inline double gridcal_max_(double a, double b) {{ return b > a ? b : a; }} /* Python max(a, b) */
static inline double gridcal_min_(double a, double b) {{ return b < a ? b : a; }} /* Python min(a, b) */

/* natural log, x >= 0 (plog) */
static inline double gridcal_log_(double x)
{{
    int e, j;
    double m, f, s, z, p, hs, de;
    if (!(x > 0.0)) return -HUGE_VAL;
    if (x == HUGE_VAL) return HUGE_VAL;
    m = frexp(x, &e);
    if (m < {d(P.SQRT_HALF)}) {{
        m = m * 2.0;
        e = e - 1;
    }}
    f = m - 1.0;
    s = f / (2.0 + f);
    z = s * s;
    p = 1.0 / (2.0 * {P.LOG_TERMS}.0 + 1.0);
    for (j = {P.LOG_TERMS - 1}; j > 0; j--) p = 1.0 / (2.0 * (double)j + 1.0) + z * p;
    hs = s + s;
    de = (double)e;
    return de * {d(P.LN2_HI)} + (hs + (hs * (z * p) + de * {d(P.LN2_LO)}));
}}

/* e^x (pexp) */
static inline double gridcal_exp_(double x)
{{
    int j;
    double k, t, p;
    if (x != x) return x;
    if (x > {d(P.EXP_OVERFLOW)}) return HUGE_VAL;
    if (x < {d(P.EXP_UNDERFLOW)}) return 0.0;
    k = floor(x * {d(P.INV_LN2)} + 0.5);
    t = (x - k * {d(P.LN2_HI)}) - k * {d(P.LN2_LO)};
    p = 1.0;
    for (j = {P.EXP_TERMS}; j > 0; j--) p = 1.0 + (t / (double)j) * p;
    return ldexp(p, (int)k);
}}

/* x^y, x >= 0 (ppow) */
static inline double gridcal_pow_(double x, double y)
{{
    if (y == 0.0) return 1.0;
    if (x == 0.0) return y > 0.0 ? 0.0 : HUGE_VAL;
    return gridcal_exp_(y * gridcal_log_(x));
}}

/* nearest integer, ties to even, 0 <= x < 2^52 (round_half_even) */
static inline double gridcal_round_(double x)
{{
    double f = floor(x), d = x - f;
    if (d > 0.5) return f + 1.0;
    if (d < 0.5) return f;
    return fmod(f, 2.0) != 0.0 ? f + 1.0 : f;
}}

/* ---- grid box (models.portable.grid_extent = models.stats.grid_box) -----------------
 * ext = extents of the grid box of the scene box [lo, hi]: a flat or zero-extent axis is
 * widened to {P.MIN_EXTENT_FRACTION:g} x the longest extent (a point scene to
 * max({P.POINT_SCENE_EXTENT_FRACTION:g} x |coordinates|, {P.MIN_ABSOLUTE_EXTENT:g})).
 * Returns 0, or -1 for NaN/Inf corners or hi < lo. */
static inline int gridcal_grid_extent(const double lo[3], const double hi[3], double ext[3])
{{
    double e[3], emax, width, amax, a, b, centre;
    int i, j;
    for (i = 0; i < 3; i++) {{
        ext[i] = 0.0;
        if (!gridcal_finite_(lo[i]) || !gridcal_finite_(hi[i])) return -1;
    }}
    for (i = 0; i < 3; i++)
        if (hi[i] < lo[i]) return -1;
    for (i = 0; i < 3; i++) e[i] = hi[i] - lo[i];
    emax = gridcal_max_(gridcal_max_(e[0], e[1]), e[2]);
    if (emax > 0.0) {{
        width = {d(P.MIN_EXTENT_FRACTION)} * emax;
    }} else {{
        amax = 0.0;
        for (i = 0; i < 3; i++) amax = gridcal_max_(amax, fabs(lo[i]));
        for (i = 0; i < 3; i++) amax = gridcal_max_(amax, fabs(hi[i]));
        width = gridcal_max_({d(P.POINT_SCENE_EXTENT_FRACTION)} * amax, {d(P.MIN_ABSOLUTE_EXTENT)});
    }}
    for (i = 0; i < 3; i++) {{
        a = lo[i];
        b = hi[i];
        if (e[i] < width) {{
            centre = 0.5 * a + 0.5 * b;
            a = centre - 0.5 * width;
            b = centre + 0.5 * width;
        }}
        for (j = 0; j < 64; j++) {{
            if (b - a > 0.0) break;
            a = nextafter(a, -HUGE_VAL);
            b = nextafter(b, HUGE_VAL);
        }}
        if (!gridcal_finite_(a) || !gridcal_finite_(b)) return -1;
        ext[i] = b - a;
    }}
    return 0;
}}

/* ---- cells -> per-axis resolution (models.portable.resolution_for_cells) ------------
 * n_i = d_i cbrt(cells / (d_x d_y d_z)) in log space, rounded half to even, clamped to
 * [1, GRIDCAL_MAX_CELLS_PER_AXIS], product clamped to GRIDCAL_MAX_TOTAL_CELLS.
 * cells > 0 (inf is clamped); ext: 3 finite extents > 0.  Returns 0, or -1 (out = 1 1 1). */
static inline int gridcal_resolution_for_cells(double cells, const double ext[3], int out[3])
{{
    double log_m, l[3], third, cap, v, q, shrink;
    long long n[3], prod;
    int i, k, it;
    out[0] = out[1] = out[2] = 1;
    if (!(cells > 0.0)) return -1;
    for (i = 0; i < 3; i++)
        if (!(gridcal_finite_(ext[i]) && ext[i] > 0.0)) return -1;
    log_m = gridcal_min_(gridcal_log_(cells), gridcal_log_((double)GRIDCAL_MAX_TOTAL_CELLS) + 1.0);
    for (i = 0; i < 3; i++) l[i] = gridcal_log_(ext[i]);
    third = (log_m - ((l[0] + l[1]) + l[2])) / 3.0;
    cap = gridcal_log_((double)GRIDCAL_MAX_CELLS_PER_AXIS) + 1.0;
    for (i = 0; i < 3; i++) {{
        v = gridcal_round_(gridcal_exp_(gridcal_min_(l[i] + third, cap)));
        v = gridcal_min_(gridcal_max_(v, 1.0), (double)GRIDCAL_MAX_CELLS_PER_AXIS);
        n[i] = (long long)v;
    }}
    for (it = 0; it < 8; it++) {{
        prod = n[0] * n[1] * n[2];
        if (prod <= (long long)GRIDCAL_MAX_TOTAL_CELLS) break;
        k = (n[0] > 1) + (n[1] > 1) + (n[2] > 1);
        q = (double)GRIDCAL_MAX_TOTAL_CELLS / (double)prod;
        shrink = k == 1 ? q : (k == 2 ? sqrt(q) : gridcal_pow_(q, 1.0 / 3.0));
        for (i = 0; i < 3; i++)
            if (n[i] > 1) n[i] = (long long)gridcal_max_(floor((double)n[i] * shrink), 1.0);
    }}
    while (n[0] * n[1] * n[2] > (long long)GRIDCAL_MAX_TOTAL_CELLS) {{
        i = (n[0] >= n[1] && n[0] >= n[2]) ? 0 : (n[1] >= n[2] ? 1 : 2);
        n[i] -= 1;
    }}
    for (i = 0; i < 3; i++) out[i] = (int)n[i];
    return 0;
}}

/* ---- the talk's closed forms per level (models.portable.paper_level_cells) ----------
 * cells[l] = m_l^3, l = 0..levels-1 (top first), of the optimal levels-level grid of n
 * points (lines = 0) or lines (lines = 1) on a manifold through k m^2 cells of each grid.
 * n, r, k > 0; 1 <= levels <= GRIDCAL_MAX_LEVELS.  Returns 0 or -1. */
static inline int gridcal_paper_level_cells(double n, double r, int levels, double k, int lines, double cells[])
{{
    double p[GRIDCAL_MAX_LEVELS], a[GRIDCAL_MAX_LEVELS], pp, aa, c, m, nl;
    int i, depth, remaining;
    if (!gridcal_positive_(n) || !gridcal_positive_(r) || !gridcal_positive_(k)) return -1;
    if (levels < 1 || levels > GRIDCAL_MAX_LEVELS) return -1;
    if (!lines) {{
        p[0] = 1.0 / 3.0;
        a[0] = 1.5 * gridcal_pow_(2.0 * r, 1.0 / 3.0);
    }} else {{
        p[0] = 0.5;
        a[0] = 2.0 * sqrt(r);
    }}
    for (i = 1; i < levels; i++) {{
        pp = p[i - 1];
        aa = a[i - 1];
        if (!lines) {{
            c = gridcal_pow_(2.0 * pp * aa * gridcal_pow_(k, 1.0 - pp), 1.0 / (2.0 * pp + 1.0));
            p[i] = pp / (2.0 * pp + 1.0);
            a[i] = (1.0 + 1.0 / (2.0 * pp)) * c;
        }} else {{
            c = gridcal_pow_(pp * aa * gridcal_pow_(k, 1.0 - pp), 1.0 / (pp + 1.0));
            p[i] = pp / (pp + 1.0);
            a[i] = (1.0 + 1.0 / pp) * c;
        }}
    }}
    nl = n;
    for (depth = 0; depth < levels; depth++) {{
        remaining = levels - depth;
        if (remaining == 1) {{
            cells[depth] = !lines ? 2.0 * nl * r : gridcal_pow_(nl * r, 1.5);
            break;
        }}
        pp = p[remaining - 2];
        aa = a[remaining - 2];
        if (!lines) {{
            m = gridcal_pow_(2.0 * pp * aa * gridcal_pow_(k, 1.0 - pp) * gridcal_pow_(nl, pp), 1.0 / (2.0 * pp + 1.0));
            nl = nl / (k * m * m);
        }} else {{
            m = gridcal_pow_(pp * aa * gridcal_pow_(k, 1.0 - pp) * gridcal_pow_(nl, pp), 1.0 / (pp + 1.0));
            nl = nl / (k * m);
        }}
        cells[depth] = m * m * m;
    }}
    return 0;
}}

/* ---- paper fidelity resolutions (models.portable.paper_resolutions) -----------------
 * Resolution of level `level` (1 = top) of a `levels`-level grid for scene_class
 * GRIDCAL_COMPACT / GRIDCAL_LONG_SKINNY / GRIDCAL_MIXED, n primitives, scene box [lo, hi],
 * k = E2 / V^(2/3) of the scene (6 for a cube; not finite -> 6; at least {P.K_MIN:g}) and
 * r = T_int / T_step.  Level l + 1 is the grid inside one cell of level l.  n < 1 gives
 * 1 1 1.  Returns 0, or -1 on bad input (out = 1 1 1). */
static inline int gridcal_paper_resolution(int scene_class, int levels, int level, double n, const double lo[3],
                                           const double hi[3], double k, double r, int out[3])
{{
    double ext[3], cells[GRIDCAL_MAX_LEVELS];
    int res[3], depth, i;
    out[0] = out[1] = out[2] = 1;
    if (n != n) return -1;
    if (gridcal_grid_extent(lo, hi, ext) != 0) return -1;
    if (!gridcal_positive_(r)) return -1;
    if (levels < 1 || levels > GRIDCAL_MAX_LEVELS || level < 1 || level > levels) return -1;
    if (scene_class != GRIDCAL_COMPACT && scene_class != GRIDCAL_LONG_SKINNY && scene_class != GRIDCAL_MIXED)
        return -1;
    if (n < 1.0) return 0;
    k = gridcal_finite_(k) ? gridcal_max_(k, {d(P.K_MIN)}) : {d(P.K_CUBE)};
    if (gridcal_paper_level_cells(n, r, levels, k, scene_class == GRIDCAL_LONG_SKINNY, cells) != 0) return -1;
    for (depth = 0; depth < levels; depth++) {{
        if (gridcal_resolution_for_cells(cells[depth], ext, res) != 0) return -1;
        if (depth + 1 == level)
            for (i = 0; i < 3; i++) out[i] = res[i];
        for (i = 0; i < 3; i++) ext[i] = ext[i] / (double)res[i];
    }}
    return 0;
}}

/* ---- the general model (models.portable.general_cells) ------------------------------
 * Total cells V / h^3 at the optimal cubic cell side h, the positive root of
 * 2 N r h^3 + E1 r h^2 - V = 0 (exact overlap, no mailbox, rays never terminate).
 * n, r > 0; e1 >= 0 (sum over triangles of their bounding-box L1 extents; 0 gives the
 * points law 2 N r); ext: the grid box extents.  Returns 0, or -1 on bad input. */
static inline int gridcal_general_cells(double n, double e1, const double ext[3], double r, double *cells)
{{
    double a, b, log_c, log_ha, beta, x, fx, dfx;
    int it;
    *cells = 1.0;
    if (!gridcal_positive_(n) || !gridcal_positive_(r)) return -1;
    if (!(gridcal_finite_(e1) && e1 >= 0.0)) return -1;
    a = 2.0 * n * r;
    if (a == HUGE_VAL) {{
        *cells = HUGE_VAL;
        return 0;
    }}
    b = r * e1;
    log_c = (gridcal_log_(ext[0]) + gridcal_log_(ext[1])) + gridcal_log_(ext[2]);
    log_ha = (log_c - gridcal_log_(a)) / 3.0;
    beta = b * gridcal_exp_(2.0 * log_ha - log_c);
    if (!(beta < HUGE_VAL)) return -1;
    x = gridcal_min_(1.0, 1.0 / sqrt(gridcal_max_(beta, 1e-300)));
    for (it = 0; it < {P.CUBIC_NEWTON_ITERATIONS}; it++) {{
        fx = x * x * (x + beta) - 1.0;
        dfx = x * (3.0 * x + 2.0 * beta);
        x = x - fx / dfx;
    }}
    *cells = a / (x * x * x);
    return 0;
}}

/* General-model resolution for n triangles with edge sum e1 in the scene box [lo, hi]
 * (models.portable.general_resolution).  n < 1 gives 1 1 1.  Returns 0 or -1. */
static inline int gridcal_general_resolution_r(double n, double e1, const double lo[3], const double hi[3],
                                               double r, int out[3])
{{
    double ext[3], cells;
    out[0] = out[1] = out[2] = 1;
    if (n != n) return -1;
    if (gridcal_grid_extent(lo, hi, ext) != 0) return -1;
    if (n < 1.0) return gridcal_positive_(r) ? 0 : -1;
    if (gridcal_general_cells(n, e1, ext, r, &cells) != 0) return -1;
    return gridcal_resolution_for_cells(cells, ext, out);
}}

/* Scene class from the triangles' aspect ratios AR = longest_edge^2 / (2 area)
 * (models.portable.scene_class_code = models.stats.scene_class): n_degenerate of
 * n_triangles degenerate, median and 95th percentile of AR over the others.
 * Returns GRIDCAL_COMPACT, GRIDCAL_LONG_SKINNY, GRIDCAL_MIXED, or -1 for n_triangles <= 0. */
static inline int gridcal_scene_class(double n_triangles, double n_degenerate, double aspect_median,
                                      double aspect_p95)
{{
    if (!(n_triangles > 0.0)) return -1;
    if (n_degenerate / n_triangles > {d(P.DEGENERATE_FRACTION_SKINNY)}) return GRIDCAL_LONG_SKINNY;
    if (aspect_median <= {d(P.AR_COMPACT_MEDIAN_MAX)} && aspect_p95 <= {d(P.AR_COMPACT_P95_MAX)}) return GRIDCAL_COMPACT;
    if (aspect_median >= {d(P.AR_SKINNY_MEDIAN_MIN)}) return GRIDCAL_LONG_SKINNY;
    return GRIDCAL_MIXED;
}}

/* ---- with this host's ratio GRIDCAL_RATIO -------------------------------------------
 * Single-level grid for a scene class: n triangles, scene bounding box [lo, hi]. */
static inline int gridcal_compact(double n, const double lo[3], const double hi[3], int out[3])
{{
    return gridcal_paper_resolution(GRIDCAL_COMPACT, 1, 1, n, lo, hi, {d(P.K_CUBE)}, GRIDCAL_RATIO, out);
}}
static inline int gridcal_long_skinny(double n, const double lo[3], const double hi[3], int out[3])
{{
    return gridcal_paper_resolution(GRIDCAL_LONG_SKINNY, 1, 1, n, lo, hi, {d(P.K_CUBE)}, GRIDCAL_RATIO, out);
}}
static inline int gridcal_mixed(double n, const double lo[3], const double hi[3], int out[3])
{{
    return gridcal_paper_resolution(GRIDCAL_MIXED, 1, 1, n, lo, hi, {d(P.K_CUBE)}, GRIDCAL_RATIO, out);
}}
/* Level `level` (1 = top) of a `levels`-level grid; k = E2 / V^(2/3) if known, else 6. */
static inline int gridcal_nested(int scene_class, int levels, int level, double n, const double lo[3],
                                 const double hi[3], double k, int out[3])
{{
    return gridcal_paper_resolution(scene_class, levels, level, n, lo, hi, k, GRIDCAL_RATIO, out);
}}
/* Single-level grid of the general model when the caller knows E1 (any mesh). */
static inline int gridcal_general(double n, double e1, const double lo[3], const double hi[3], int out[3])
{{
    return gridcal_general_resolution_r(n, e1, lo, hi, GRIDCAL_RATIO, out);
}}
"""


# ---------------------------------------------------------------------------------------
# the header
# ---------------------------------------------------------------------------------------

def _constant_block(macro, what, unit, value, interval, source) -> str:
    iv = "no interval" if interval is None else f"95% interval [{_fmt(interval[0])}, {_fmt(interval[1])}]"
    return (f"/* {what}: {unit}; median {_fmt(value)}, {iv}; {source}. */\n"
            f"#ifndef {macro}\n#define {macro} {_c_double(value)}\n#endif\n")


def header_constants(cal: dict | None = None, ratio: float | None = None, rays: str | None = None) -> dict:
    """``{key: {macro, unit, median, ci95}}`` of the constants the header defines.

    cal : a validated calibration (calibrate.calfile.load), or ratio : r alone.
    rays : the ray set to export for: the calibration's fit of that set alone when
        it has one (``by_rays``, as ``predict --rays`` uses), else its pooled fit.
    """
    from .calfile import fit_for_rays

    out = {}
    if cal is None:
        if ratio is None or not (math.isfinite(float(ratio)) and float(ratio) > 0):
            raise ValueError("give a calibration or a ratio r > 0")
        key, macro, _, unit = CONSTANTS[-1]
        return {key: dict(macro=macro, unit=unit, median=float(ratio), ci95=None)}
    consts = fit_for_rays(cal, rays)[0]["constants"]
    for key, macro, _, unit in CONSTANTS:
        c = consts.get(key)
        if c is None:
            continue
        ci = c.get("ci95")
        out[key] = dict(macro=macro, unit=unit, median=float(c["median"]),
                        ci95=None if ci is None else [float(ci[0]), float(ci[1])])
    if "ratio" not in out:
        raise ValueError("the calibration lacks the ratio")
    if not out["ratio"]["median"] > 0:
        raise ValueError("the calibration's ratio must be > 0")
    return out


def header_text(cal: dict | None = None, ratio: float | None = None, source: str | None = None,
                rays: str | None = None) -> str:
    """The complete header (str) for a calibration or a ratio alone.

    cal : validated calibration dict; ratio : r > 0 (when cal is None);
    source : the calibration file's name, shown in the provenance;
    rays : the ray set exported for (see :func:`header_constants`).
    """
    from .calfile import fit_for_rays

    consts = header_constants(cal, ratio, rays)
    block, fitted_on = (None, None) if cal is None else fit_for_rays(cal, rays)
    lines = ["/* grid_tuning.h: grid resolutions for this host, from gridcal's `calibrate export`.",
             " *",
             " * Provenance:"]
    if cal is None:
        lines.append(" *   no calibration: r = T_int / T_step was given on the command line (--ratio);")
        lines.append(" *   the time constants T_setup, T_step, T_int, T_sub are not defined.")
    else:
        fp = cal.get("fingerprint") or {}
        if source is not None:
            lines.append(f" *   calibration file: {sanitize_comment(source)}")
        lines.append(f" *   calibration schema version: {sanitize_comment(cal.get('schema_version'))}")
        for key, label in PROVENANCE_KEYS:
            if fp.get(key) is not None:
                lines.append(f" *   {label}: {sanitize_comment(fp[key])}")
        lines.append(f" *   constants fitted on: {sanitize_comment(fitted_on) + ' rays alone' if fitted_on else 'all ray sets'}")
        diag = block.get("diagnostics") or {}
        if diag.get("converged") is not None:
            lines.append(f" *   posterior converged: {sanitize_comment(diag.get('converged'))}")
    lines += [" *",
              " * Every constant is inside #ifndef: define it before including this file to override",
              " * it (e.g. -DGRIDCAL_RATIO=1.5).  The resolutions use GRIDCAL_RATIO only.",
              " * Functions return 0 and write out[3] = (nx, ny, nz), or return -1 on bad input",
              " * (NaN/Inf, hi < lo, n/r out of range) and write 1 1 1.  They equal gridcal's Python",
              " * predictions (models.portable) bit for bit when built with -ffp-contract=off and",
              " * without -ffast-math.  Link with -lm.",
              " *",
              " * Use: lo, hi = the scene's bounding box; n = triangles; e1 = sum over triangles of",
              " * their bounding-box extents x + y + z (when known).  int res[3];",
              " *   gridcal_general(n, e1, lo, hi, res);           any mesh, single level",
              " *   gridcal_compact(n, lo, hi, res);               the talk's points law (also _long_skinny, _mixed)",
              " *   gridcal_nested(GRIDCAL_COMPACT, 2, 1, n, lo, hi, 6.0, res);  top of a 2-level grid",
              " *   gridcal_nested(GRIDCAL_COMPACT, 2, 2, n, lo, hi, 6.0, res);  each of its subgrids",
              " */",
              "#ifndef GRIDCAL_GRID_TUNING_H",
              "#define GRIDCAL_GRID_TUNING_H",
              "",
              "#include <math.h>",
              ""]
    text = "\n".join(lines) + "\n"
    source_note = "given with --ratio" if cal is None else (
        f"median of the posterior (in-context fit, {sanitize_comment(fitted_on)} rays)" if fitted_on
        else "median of the posterior (in-context fit)")
    for key, macro, what, unit in CONSTANTS:
        if key not in consts:
            if cal is not None and key == "t_sub_ns":
                text += "/* T_sub: not measured in this calibration (no configuration entered a subgrid). */\n"
            continue
        c = consts[key]
        text += _constant_block(macro, what, unit, c["median"], c["ci95"], source_note)
        if key == "t_mem_ns":
            from .calfile import cache_bytes_of

            cache = cache_bytes_of(cal)
            text += ("/* The cache T_mem was measured against, the middle of a spread of sizes one octave "
                     "wide (models/memory.py): bytes. */\n"
                     f"#ifndef GRIDCAL_CACHE_BYTES\n#define GRIDCAL_CACHE_BYTES {int(cache)}.0\n#endif\n")
    text += _c_functions()
    text += "\n#endif /* GRIDCAL_GRID_TUNING_H */\n"
    return text


def export(path=DEFAULT_HEADER, *, calibration=None, ratio=None, rays: str | None = "isotropic") -> dict:
    """Write the header atomically; return ``{header, constants, fitted_on, functions}``.

    calibration : path of a calibration file (default ./calibration.json when ratio is None).
    ratio : r = T_int / T_step alone.
    rays : the ray set the resolutions are for (default isotropic, as ``predict``); the
        calibration's fit of that set alone when it has one, else its pooled fit.
    """
    from . import calfile

    if ratio is not None and calibration is not None:
        raise UserError("give either --calibration FILE or --ratio R, not both")
    cal = source = None
    if ratio is None:
        source = Path(calibration) if calibration is not None else Path(DEFAULT_CALIBRATION)
        if calibration is None and not source.exists():
            raise UserError(f"no calibration: ./{DEFAULT_CALIBRATION} does not exist; run `calibrate run` first, "
                            "pass --calibration FILE, or give your own ratio with --ratio R")
        cal = calfile.load(source)
    text = header_text(cal, ratio, source=None if source is None else source.name, rays=rays)
    out = Path(path)
    atomic_write_text(out, text, encoding="ascii")
    return dict(header=str(out), constants=header_constants(cal, ratio, rays),
                fitted_on=None if cal is None else calfile.fit_for_rays(cal, rays)[1], functions=list(FUNCTIONS))


# ---------------------------------------------------------------------------------------
# command line
# ---------------------------------------------------------------------------------------

def add_parser(sub):
    """Register the ``export`` verb on an argparse subparsers object; returns its parser."""
    from .predict import RAY_KINDS, add_constants_options

    help_text = "write this host's constants and grid-resolution functions as a C header"
    sp = sub.add_parser("export", help=help_text, description=help_text)
    sp.add_argument("--json", action="store_true", help="machine-readable output on stdout")
    sp.add_argument("--quiet", action="store_true", help="print nothing but errors")
    add_constants_options(sp, "export your own T_int/T_step alone (no time constants)")
    sp.add_argument("--header", default=DEFAULT_HEADER, metavar="FILE",
                    help=f"header to write (default {DEFAULT_HEADER})")
    sp.add_argument("--rays", default="isotropic", choices=RAY_KINDS,
                    help="the rays your renderer traces: a calibration that fitted that ray set alone gives "
                         "its constants (default isotropic, as predict)")
    sp.set_defaults(func=cmd_export)
    return sp


def cmd_export(args) -> int:
    """Run the ``export`` verb."""
    result = export(args.header, calibration=args.calibration, ratio=args.ratio, rays=args.rays)
    if args.json:
        sys.stdout.write(json.dumps(result, indent=2, allow_nan=False) + "\n")
    elif not args.quiet:
        r = result["constants"]["ratio"]
        print(f"wrote {result['header']}: r = {_fmt(r['median'])}, {len(result['constants'])} constants, "
              f"{len(result['functions'])} functions ({', '.join(FUNCTIONS[:5])}, ...)")
    return 0
