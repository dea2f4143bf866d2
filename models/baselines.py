"""Grid-resolution heuristics renderers use today, as named baselines.

Each takes the scene's triangle count and grid box (or :class:`SceneStats`) and
returns resolutions, so ``calibrate predict`` can print them beside its own.
"""

from __future__ import annotations

import numpy as np

from .closed_forms import MAX_CELLS_PER_AXIS, MAX_TOTAL_CELLS, cells_to_resolution
from .stats import SceneStats

#: pbrt v1/v2 GridAccel: voxels along the longest axis = 3 * N^(1/3), at most 64 per axis.
PBRT_VOXELS_PER_CUBE_ROOT = 3.0
PBRT_MAX_VOXELS_PER_AXIS = 64
#: Manta RecursiveGrid: the single tuned constant ("found 8 to work well").
MANTA_SCALE = 8.0
#: Cleary & Wyvill (1988): lambda N cells, lambda = 5 by default.
CLEARY_LAMBDA = 5.0
#: Kalojanov, Billeter, Slusallek, "Two-level grids for ray tracing on GPUs" (2011):
#: top-level density 1/16 and leaf density 1.2 references per cell.
KALOJANOV_TOP_DENSITY = 1.0 / 16.0
KALOJANOV_LEAF_DENSITY = 1.2


def _n_extent(stats_or_n, extent=None):
    if isinstance(stats_or_n, SceneStats):
        return float(stats_or_n.n_triangles), np.asarray(stats_or_n.extent, dtype=np.float64)
    n = float(stats_or_n)
    if not n >= 1:
        raise ValueError(f"triangle count must be >= 1, got {stats_or_n!r}")
    if extent is None:
        raise ValueError("extent is required when a triangle count is given")
    d = np.asarray(extent, dtype=np.float64)
    if d.shape != (3,) or not np.all(np.isfinite(d)) or np.any(d <= 0):
        raise ValueError(f"extent must be 3 finite positive lengths, got {extent!r}")
    return n, d


def pbrt_grid(stats_or_n, extent=None) -> tuple[int, int, int]:
    """pbrt v1/v2 ``GridAccel``: ``3 N^(1/3)`` voxels along the longest axis, others
    proportional (``Round2Int(delta[axis] * voxelsPerUnitDist)``), clamped to [1, 64]."""
    n, d = _n_extent(stats_or_n, extent)
    per_unit = PBRT_VOXELS_PER_CUBE_ROOT * n ** (1.0 / 3.0) / d.max()
    res = np.clip(np.floor(d * per_unit + 0.5), 1, PBRT_MAX_VOXELS_PER_AXIS).astype(int)
    return int(res[0]), int(res[1]), int(res[2])


def manta_level_cells(n, levels=1, depth=0, scale=MANTA_SCALE) -> float:
    """Manta ``RecursiveGrid`` per-level rule: cells of a (sub)grid holding n triangles.

    Per axis ``m = (scale n)^(1 / (2L + 1 - 2 depth))``, so total cells
    ``M = (scale n)^(3 / (2L + 1 - 2 depth))``.  For L = 1 this is ``M = 8 N`` ("total
    cells 8N"); at the top of an L-level grid ``M ~ N^(3/(2L+1))``, the talk's L-level
    law; a subgrid at depth d is sized as the top of an (L - d)-level grid.  DESIGN §2
    writes ``M = (8 N)^(1/(2L+1))``: that is the per-axis m, not the total M.
    """
    if int(levels) != levels or levels < 1 or int(depth) != depth or not 0 <= depth < levels:
        raise ValueError(f"need integer levels >= 1 and 0 <= depth < levels, got {levels}, {depth}")
    n = float(n)
    if not n > 0 or not np.isfinite(n):
        raise ValueError(f"n must be finite and > 0, got {n!r}")
    return float((scale * n) ** (3.0 / (2 * levels + 1 - 2 * depth)))


def manta_recursive_grid(stats_or_n, extent=None, levels=1, *, max_per_axis=MAX_CELLS_PER_AXIS,
                         max_total=MAX_TOTAL_CELLS) -> tuple[int, int, int]:
    """Manta ``RecursiveGrid`` top-level resolution: ``(8 N)^(3/(2L+1))`` cells, cubic-ish."""
    n, d = _n_extent(stats_or_n, extent)
    return cells_to_resolution(manta_level_cells(n, levels, 0), d, max_per_axis=max_per_axis,
                               max_total=max_total)


def cleary_grid(stats_or_n, extent=None, lam=CLEARY_LAMBDA, *, max_per_axis=MAX_CELLS_PER_AXIS,
                max_total=MAX_TOTAL_CELLS) -> tuple[int, int, int]:
    """Cleary & Wyvill (1988): ``lambda N`` cells (lambda = 5), cubic-ish cells."""
    n, d = _n_extent(stats_or_n, extent)
    if not lam > 0:
        raise ValueError(f"lambda must be > 0, got {lam!r}")
    return cells_to_resolution(lam * n, d, max_per_axis=max_per_axis, max_total=max_total)


def kalojanov_leaf_resolution(n_refs, cell_extent, density=KALOJANOV_LEAF_DENSITY) -> tuple[int, int, int]:
    """Kalojanov et al. 2011 leaf grid of a top cell holding ``n_refs`` references:
    ``density * n_refs`` cells via the volume formula (cubic-ish cells), at least 1."""
    d = np.asarray(cell_extent, dtype=np.float64)
    n = float(n_refs)
    if not n >= 0:
        raise ValueError(f"n_refs must be >= 0, got {n_refs!r}")
    return cells_to_resolution(max(density * n, 1.0), d)


def kalojanov_two_level(stats_or_n, extent=None, *, cell_refs=None, top_density=KALOJANOV_TOP_DENSITY,
                        leaf_density=KALOJANOV_LEAF_DENSITY):
    """Kalojanov, Billeter, Slusallek 2011 two-level grid.

    Top: ``top_density * N`` cells (``R_i = d_i cbrt(lambda N / V)``).  Leaves: each top
    cell with ``n_c`` references gets ``leaf_density * n_c`` cells.

    Parameters
    ----------
    cell_refs : optional (C,) references per non-empty top cell (from a real build).
        Without it the leaf reported is the one for the mean of ``N / top_cells``
        references per top cell, floored at 1 (the scene treated as uniform).

    Returns
    -------
    (top, leaf) : two resolutions; ``leaf`` is for the median non-empty cell.
    """
    n, d = _n_extent(stats_or_n, extent)
    top = cells_to_resolution(max(top_density * n, 1.0), d)
    cell = d / np.asarray(top, dtype=np.float64)
    if cell_refs is None:
        refs = max(n / (top[0] * top[1] * top[2]), 1.0)
    else:
        c = np.asarray(cell_refs, dtype=np.float64)
        c = c[c > 0]
        refs = float(np.median(c)) if c.size else 1.0
    return top, kalojanov_leaf_resolution(refs, cell, leaf_density)


def all_baselines(stats: SceneStats) -> dict[str, list[tuple[int, int, int]]]:
    """Every baseline for a scene: name -> list of resolutions, top level first."""
    top, leaf = kalojanov_two_level(stats)
    return {
        "pbrt-v2": [pbrt_grid(stats)],
        "manta-L1": [manta_recursive_grid(stats, levels=1)],
        "manta-L2-top": [manta_recursive_grid(stats, levels=2)],
        "cleary-lambda5": [cleary_grid(stats)],
        "kalojanov-2level": [top, leaf],
    }
