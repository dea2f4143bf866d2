"""gridcal's cost models: pure math, no clocks, no kernels.

Counts (cells stepped, triangle tests, subgrids entered per ray) are predicted
from a mesh's geometry; multiplied by a host's calibrated constants they give
the time per ray, and the resolution that minimises it.  Inputs are numpy
arrays: ``vertices (V, 3) float64``, ``faces (F, 3) int64``.  This package
imports neither ``calibrate`` nor the compiled kernels (jax only when a
posterior is propagated).
"""

from .baselines import all_baselines, cleary_grid, kalojanov_two_level, manta_recursive_grid, pbrt_grid
from .closed_forms import (cells_to_resolution, empirical_cells, l_level_cells, lines_cells, points_cells,
                           two_level_lines, two_level_points)
from .effects import EFFECT_TOLERANCE, rays_stop_on_entry, select_effects, termination_fraction
from .general import Terms, optimal_cell_size, optimal_uniform, predict_uniform, steps_per_ray
from .memory import lines_beyond_cache, miss_fraction
from .nested import choose_levels, nested_counts, optimal_nested
from .portable import general_resolution, paper_resolutions, resolution_for_cells
from .stats import SceneStats, TerminationSample, grid_box, scene_class, scene_stats, triangle_geometry
from .uncertainty import posterior_ns, posterior_optimum

__all__ = [
    # scene statistics
    "SceneStats", "TerminationSample", "grid_box", "scene_class", "scene_stats", "triangle_geometry",
    # the talk's closed forms
    "points_cells", "lines_cells", "two_level_points", "two_level_lines", "l_level_cells", "empirical_cells",
    "cells_to_resolution",
    # portable resolutions (what the exported C header computes, bit for bit)
    "paper_resolutions", "general_resolution", "resolution_for_cells",
    # today's heuristics
    "all_baselines", "pbrt_grid", "manta_recursive_grid", "cleary_grid", "kalojanov_two_level",
    # the general model
    "Terms", "steps_per_ray", "predict_uniform", "optimal_cell_size", "optimal_uniform",
    "nested_counts", "optimal_nested", "choose_levels",
    # the memory effect
    "miss_fraction", "lines_beyond_cache",
    # effects and uncertainty
    "EFFECT_TOLERANCE", "select_effects", "termination_fraction", "rays_stop_on_entry",
    "posterior_optimum", "posterior_ns",
]
