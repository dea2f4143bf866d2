"""Which cells of a uniform grid a batch of rays reads, and how much of what it reads a cache keeps.

The memory term of the cost model (:mod:`models.memory`) charges a line read from a grid
larger than the cache ``1 - C/F`` of a miss, F the whole grid: right when every cell is read
alike, as isotropic lines that never stop read them (Crofton).  Rays that stop read the
cells where they stop, and not alike: on ``cylinder19996`` the two end caps hold 85% of the
references at 65x65x12 cells, in cells that only the lines entering through the box's end
faces reach, while every ray that hits the side reads one of a few thousand side cells
(docs/calibration.md, "What rays read of a big grid").  This module counts, for a batch of
rays, how often each cell is entered, by the same 3D-DDA walk the kernels make (every cell
from the box entry to the one holding the first hit), so that
:func:`models.memory.weighted_miss_fraction` can say which share of the bytes read misses.

A measuring aid, not part of a prediction: the walk is numpy, a few seconds for 16,384
rays on a grid of a million cells; the counts of cells entered per ray equal the
instrumented kernel's steps (tests/test_reach.py).
"""

from __future__ import annotations

import numpy as np

from ._grid import Grid
from .predict import BYTES_PER_CELL, BYTES_PER_REFERENCE
from .rays import box_chords
from models.memory import BITMAP_BYTES_PER_CELL, miss_fraction, weighted_miss_fraction

__all__ = ["cell_entries", "cell_bytes", "read_miss_fraction"]


def cell_entries(grid: Grid, origins, directions) -> tuple[np.ndarray, np.ndarray]:
    """(entries per cell, cells entered per ray) of ``grid`` (uniform) for rays that stop at their
    first hit.

    entries : (nx*ny*nz,) int64, cell ``x + nx*(y + ny*z)`` (the kernels' order).
    per_ray : (n,) int64, the cells each ray enters (0 for a ray that misses the box).
    A ray enters the cell where it enters the box (:func:`calibrate.rays.box_chords`), then the next cell along it while the
    boundary it crosses comes no later than its first hit (``Grid.intersect``) and the box
    exit; ties between axes go to x, then y, as the kernels' walk breaks them.
    """
    if grid.info.get("levels", 1) != 1:
        raise ValueError("cell_entries walks a uniform grid (one level)")
    o = np.ascontiguousarray(origins, dtype=np.float64)
    d = np.ascontiguousarray(directions, dtype=np.float64)
    if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape:
        raise ValueError(f"origins and directions must both be (n, 3), got {o.shape} and {d.shape}")
    res = np.asarray(grid.resolution, dtype=np.int64)
    lo = np.asarray(grid.info["box_lo"], dtype=np.float64)
    hi = np.asarray(grid.info["box_hi"], dtype=np.float64)
    cell = (hi - lo) / res
    t_hit, _ = grid.intersect(o, d)
    n = o.shape[0]
    per_ray = np.zeros(n, dtype=np.int64)
    entries = np.zeros(int(np.prod(res)), dtype=np.int64)
    t_in, t_out = box_chords(o, d, lo, hi)
    t_in = np.maximum(t_in, 0.0)
    rows = np.nonzero(t_in <= t_out)[0]
    if rows.size == 0:
        return entries, per_ray
    o, d = o[rows], d[rows]
    t_stop = np.minimum(t_out[rows], t_hit[rows])
    idx = np.clip(np.floor((o + t_in[rows, None] * d - lo) / cell).astype(np.int64), 0, res - 1)
    step = np.where(d > 0, 1, -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t_next = np.where(d != 0, (lo + (idx + (d > 0)) * cell - o) * inv, np.inf)
        t_delta = np.where(d != 0, cell * np.abs(inv), np.inf)
    count = np.zeros(rows.size, dtype=np.int64)
    alive = np.arange(rows.size)
    while alive.size:
        i = idx[alive]
        np.add.at(entries, i[:, 0] + res[0] * (i[:, 1] + res[1] * i[:, 2]), 1)
        count[alive] += 1
        axis = np.argmin(t_next[alive], axis=1)
        crossing = t_next[alive, axis]
        idx[alive, axis] += step[alive, axis]
        t_next[alive, axis] += t_delta[alive, axis]
        inside = (idx[alive, axis] >= 0) & (idx[alive, axis] < res[axis])
        alive = alive[(crossing <= t_stop[alive]) & inside]
    per_ray[rows] = count
    return entries, per_ray


def cell_bytes(grid: Grid) -> np.ndarray:
    """(nx*ny*nz,) bytes a ray reads when it enters each cell of a uniform grid: the cell's
    occupancy bit, and where it is set the cell's record and its references' triangle copies
    (kernels/gc_internal.h)."""
    refs = np.asarray(grid.top_counts(), dtype=np.float64).ravel()
    return BITMAP_BYTES_PER_CELL + np.where(refs > 0, BYTES_PER_CELL + BYTES_PER_REFERENCE * refs, 0.0)


def read_miss_fraction(grid: Grid, origins, directions, cache_bytes) -> dict:
    """How much of what a batch of rays reads from ``grid`` misses a cache of ``cache_bytes``.

    Returns ``weighted`` (:func:`models.memory.weighted_miss_fraction` with each cell's
    entries per ray and its bytes), ``whole`` (:func:`models.memory.miss_fraction` of the whole
    grid, what the cost model charges), ``read_bytes`` (the bytes of the cells the batch
    enters at least once), ``memory_bytes`` (the whole grid) and ``steps`` (cells entered per
    ray).
    """
    entries, per_ray = cell_entries(grid, origins, directions)
    sizes = cell_bytes(grid)
    rays = max(1, len(per_ray))
    memory = float(grid.info["memory_bytes"])
    return dict(weighted=weighted_miss_fraction(entries / rays, sizes, cache_bytes),
                whole=float(miss_fraction(memory, cache_bytes)),
                read_bytes=float(sizes[entries > 0].sum()), memory_bytes=memory,
                steps=float(per_ray.mean()) if len(per_ray) else 0.0)
