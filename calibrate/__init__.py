"""gridcal: measure this host's grid ray-tracing costs and predict optimal grid resolutions.

The public surface::

    from calibrate import Scene, Grid
    scene = Scene.from_file("bunny.ply")          # or Scene(vertices, faces), Scene.builtin("sphere")
    grid = Grid.uniform(scene, (nx, ny, nz), intersector="watertight", mailbox=True)
    grid = Grid.nested(scene, levels=2)
    t, prim = grid.intersect(origins, directions)
    steps, tests, subgrids = grid.count(origins, directions)
"""

from ._grid import Grid, Scene, brute_force

__all__ = ["Scene", "Grid", "brute_force"]
