"""The talk's closed forms (DESIGN §3.1) and the cells -> per-axis resolution rule.

Source: Ize, Shirley, Parker, "Grid Creation Strategies for Efficient Ray Tracing"
(RT 2007).  ``r = T_int / T_step``; N primitives; M total cells; m = M^(1/3) per axis.

- points (compact triangles): ``T = m + (N/m^2) r`` -> ``M = 2 N r``
- lines (long skinny):        ``T = m + (N/m) r``   -> ``M = (N r)^1.5``
- 2-level points on a manifold through ``k m1^2`` cells (k = 6 for a cube):
  ``m1^3 = (2 k^2 N r)^0.6``, ``m2^3 = (2 N r / k^3)^0.6``
- 2-level lines on a manifold (same derivation; each line crosses m1 top cells, so a
  subgrid holds ``N / (k m1)`` lines): ``m1^3 = k N r``, ``m2^3 = N r / k^2``
- L-level: top grid ``O(N^(3/(2L+1)))`` cells (points); constant from the exact
  recursion below.
- empirical single level: ``M ~ N^(7/9)`` (compact), ``M ~ N^(4/3)`` (long skinny).

All functions accept scalars or numpy arrays (broadcast) and return float64.
"""

from __future__ import annotations

import numpy as np

from . import portable as _portable
from .portable import resolution_for_cells

#: Talk's 2-level example constant: a cube's surface passes through 6 m^2 cells.
K_CUBE = _portable.K_CUBE  # 6.0
#: Proportionality constants of the talk's empirical single-level laws (cells per
#: N^(7/9) and per N^(4/3)).  The talk gives only the exponents; 1.0 is a neutral default
#: to be replaced by a fitted value.
EMPIRICAL_COMPACT_CONSTANT = 1.0
EMPIRICAL_SKINNY_CONSTANT = 1.0
EMPIRICAL_COMPACT_EXPONENT = 7.0 / 9.0
EMPIRICAL_SKINNY_EXPONENT = 4.0 / 3.0

#: Clamp on cells per axis (the C grid stores per-axis counts as 32-bit integers; 4096
#: keeps one axis of cell offsets well inside memory for any flat box).
MAX_CELLS_PER_AXIS = _portable.MAX_CELLS_PER_AXIS  # 4096
#: Clamp on total cells: 2^26 cells = 256 MiB of 32-bit cell offsets, and a flat cell
#: index x + nx*(y + ny*z) that always fits a signed 32-bit integer.
MAX_TOTAL_CELLS = _portable.MAX_TOTAL_CELLS  # 2 ** 26


def _pos(name, x):
    a = np.asarray(x, dtype=np.float64)
    if not np.all(np.isfinite(a)) or np.any(a <= 0):
        raise ValueError(f"{name} must be finite and > 0, got {x!r}")
    return a


def points_cells(n, r):
    """Single-level grid of points: ``M = 2 N r`` cells."""
    return 2.0 * _pos("n", n) * _pos("r", r)


def lines_cells(n, r):
    """Single-level grid of lines: ``M = (N r)^1.5`` cells."""
    return (_pos("n", n) * _pos("r", r)) ** 1.5


def two_level_points(n, r, k=K_CUBE):
    """2-level grid of points on a manifold: ``(m1^3, m2^3) = ((2 k^2 N r)^0.6, (2 N r / k^3)^0.6)``."""
    n, r, k = _pos("n", n), _pos("r", r), _pos("k", k)
    return (2.0 * k * k * n * r) ** 0.6, (2.0 * n * r / k ** 3) ** 0.6


def two_level_lines(n, r, k=K_CUBE):
    """2-level grid of lines on a manifold: ``(m1^3, m2^3) = (k N r, N r / k^2)``.

    Derivation (the talk's 2-level argument with lines): a ray enters ``k`` subgrids;
    each top cell holds ``N m1 / (k m1^2)`` lines, and a subgrid of lines costs
    ``2 sqrt(N2 r)`` steps at its optimum ``m2 = sqrt(N2 r)``, so
    ``T = m1 + 2 sqrt(k N r) m1^(-1/2)``, minimal at ``m1^3 = k N r``.
    """
    n, r, k = _pos("n", n), _pos("r", r), _pos("k", k)
    return k * n * r, n * r / (k * k)


def l_level_cells(n, r, levels, k=K_CUBE, kind="points") -> list:
    """Cells per level (top first) of the optimal L-level grid of points or lines on a manifold.

    Exact recursion of the talk's 2-level argument, with the same manifold constant k
    at every level (each subgrid again holds a piece of surface through ``k m^2`` of its
    cells).  Let ``C_L(N) = a_L N^p_L`` be the optimal cost (in units of T_step, setup
    excluded) of an L-level grid of N items:

    - points: ``C_1 = 1.5 (2 r N)^(1/3)``; a subgrid holds ``N / (k m^2)`` points and
      ``C_L = min_m m + k C_{L-1}(N / (k m^2))``, so
      ``m^(2p+1) = 2 p a k^(1-p) N^p`` (p, a of level L-1), ``p_L = 1/(2L+1)``:
      top cells ``m^3 ~ N^(3/(2L+1))`` as the talk states.
    - lines: ``C_1 = 2 (r N)^(1/2)``; a subgrid holds ``N / (k m)`` lines and
      ``m^(p+1) = p a k^(1-p) N^p``, ``p_L = 1/(L+1)``.

    The constant is therefore the one the recursion gives; for L = 2 it reproduces
    :func:`two_level_points` / :func:`two_level_lines` exactly, for L = 1
    :func:`points_cells` / :func:`lines_cells`.

    Returns a list of L floats (or arrays): ``m_l^3`` for l = 1..L.
    """
    if kind not in ("points", "lines"):
        raise ValueError(f"kind must be 'points' or 'lines', got {kind!r}")
    if int(levels) != levels or levels < 1:
        raise ValueError(f"levels must be an integer >= 1, got {levels!r}")
    n, r, k = _pos("n", n), _pos("r", r), _pos("k", k)
    levels = int(levels)
    # (p, a) for 1..L levels.
    if kind == "points":
        pa = [(1.0 / 3.0, 1.5 * (2.0 * r) ** (1.0 / 3.0))]
    else:
        pa = [(0.5, 2.0 * np.sqrt(r))]
    for _ in range(1, levels):
        p, a = pa[-1]
        if kind == "points":
            c = (2.0 * p * a * k ** (1.0 - p)) ** (1.0 / (2.0 * p + 1.0))
            pa.append((p / (2.0 * p + 1.0), (1.0 + 1.0 / (2.0 * p)) * c))
        else:
            c = (p * a * k ** (1.0 - p)) ** (1.0 / (p + 1.0))
            pa.append((p / (p + 1.0), (1.0 + 1.0 / p) * c))
    cells = []
    n_level = n
    for depth in range(levels):
        remaining = levels - depth
        if remaining == 1:
            m3 = points_cells(n_level, r) if kind == "points" else lines_cells(n_level, r)
            cells.append(m3)
            break
        p, a = pa[remaining - 2]  # cost law of the (remaining-1)-level subgrids
        if kind == "points":
            m = (2.0 * p * a * k ** (1.0 - p) * n_level ** p) ** (1.0 / (2.0 * p + 1.0))
            n_level = n_level / (k * m * m)
        else:
            m = (p * a * k ** (1.0 - p) * n_level ** p) ** (1.0 / (p + 1.0))
            n_level = n_level / (k * m)
        cells.append(m ** 3)
    return cells


def empirical_cells(n, kind="compact", constant=None):
    """The talk's empirical single-level laws: ``M = c N^(7/9)`` (compact) or ``c N^(4/3)``.

    ``constant`` defaults to ``EMPIRICAL_COMPACT_CONSTANT`` / ``EMPIRICAL_SKINNY_CONSTANT``.
    """
    n = _pos("n", n)
    if kind == "compact":
        c = EMPIRICAL_COMPACT_CONSTANT if constant is None else constant
        return _pos("constant", c) * n ** EMPIRICAL_COMPACT_EXPONENT
    if kind == "long-skinny":
        c = EMPIRICAL_SKINNY_CONSTANT if constant is None else constant
        return _pos("constant", c) * n ** EMPIRICAL_SKINNY_EXPONENT
    raise ValueError(f"kind must be 'compact' or 'long-skinny', got {kind!r}")


def cells_to_resolution(total_cells, extent, *, max_per_axis=MAX_CELLS_PER_AXIS,
                        max_total=MAX_TOTAL_CELLS) -> tuple[int, int, int]:
    """Per-axis resolution with near-cubic cells for a requested total cell count.

    ``n_i = d_i * cbrt(M / (d_x d_y d_z))`` (the talk's rule), computed in log space so
    no product overflows, rounded to nearest (ties to even), each clamped to
    ``[1, max_per_axis]``, then the product clamped to ``max_total`` by shrinking the
    axes that are > 1 together (cells stay as cubic as the clamp allows).  The
    arithmetic is :func:`models.portable.resolution_for_cells` (portable logarithm and
    exponential), which the exported C header reproduces bit for bit.

    Parameters
    ----------
    total_cells : float > 0 (may be huge or tiny; inf is clamped).
    extent : (3,) float64, box extents, all finite and > 0 (use :func:`models.stats.grid_box`).

    Returns
    -------
    (nx, ny, nz) : Python ints, ``1 <= n_i <= max_per_axis``, ``nx*ny*nz <= max_total``.
    """
    m = float(total_cells)
    if np.isnan(m) or m <= 0:
        raise ValueError(f"total_cells must be > 0, got {total_cells!r}")
    d = np.asarray(extent, dtype=np.float64).reshape(-1)
    if d.shape != (3,) or not np.all(np.isfinite(d)) or np.any(d <= 0):
        raise ValueError(f"extent must be 3 finite positive lengths, got {extent!r}")
    if int(max_per_axis) < 1 or int(max_total) < 1:
        raise ValueError("max_per_axis and max_total must be >= 1")
    return resolution_for_cells(m, (float(d[0]), float(d[1]), float(d[2])), int(max_per_axis), int(max_total))
