"""`calibrate render`: a picture of a scene traced through the grid, or of what each ray cost.

A pinhole camera looks at the scene's box (:func:`calibrate.rays.camera_grid`: one ray
through the centre of each pixel, the generic default view of :mod:`calibrate.rays`).
The primary rays are traced with the grid that ``calibrate predict`` recommends (or a
given resolution) and drawn as

``shaded``
    ``|n . d|`` of the hit triangle (n its unit normal, d the unit ray direction) in
    grey, the background colour where a ray misses;
``--heatmap steps`` / ``--heatmap tests``
    the cells each ray stepped through (every level) or the triangles it tested, from
    the instrumented twin (:meth:`calibrate._grid.Grid.count`, per ray), with a colour
    bar: the per-pixel cost pictures of the talk.

:func:`render` does the work and returns the arrays; :func:`add_parser` registers the
verb.  Images are PNG (matplotlib, Agg backend), written atomically.
"""

from __future__ import annotations

import io
import sys
from pathlib import Path

import numpy as np

from ._grid import Grid, Scene
from ._io import UserError, atomic_write_bytes, check_writable

HEATMAPS = ("steps", "tests")
DEFAULT_SCENE = "sphere"
DEFAULT_WIDTH = 480
DEFAULT_HEIGHT = 360
#: Largest image side (pixels): keeps a render's rays and its PNG within reason.
MAX_SIDE_PIXELS = 4096

# --- the picture ---------------------------------------------------------------------
#: Grey of a hit: SHADE_FLOOR + (1 - SHADE_FLOOR) * |n . d| (a grazing hit stays visible).
SHADE_FLOOR = 0.12
#: RGB of a miss: a blue grey that no grey shade equals, so hits and misses stay apart.
BACKGROUND_RGB = (0.20, 0.24, 0.34)
#: Colour map of the heatmaps (perceptually ordered, dark = cheap, bright = costly).
HEATMAP_CMAP = "inferno"
#: Dots per inch of the heatmap figure: a power of two, so (pixels / DPI) * DPI is exact
#: in floating point and the PNG has exactly the intended size.
HEATMAP_DPI = 128
#: Width (pixels) of the colour-bar strip right of a heatmap; the PNG is (W + this) x H.
COLORBAR_STRIP_PIXELS = 96
#: The colour scale ends at this percentile of the pixels' counts (the bar's arrow marks
#: larger ones; the title gives the true maximum).
HEATMAP_SCALE_PERCENTILE = 99.5
HEATMAP_LABELS = {"steps": "cells stepped per ray", "tests": "triangle tests per ray"}


def _check_size(value, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 1 <= int(value) <= MAX_SIDE_PIXELS:
        raise UserError(f"{what} must be a whole number of pixels from 1 to {MAX_SIDE_PIXELS}, got {value!r}")
    return int(value)


def recommended_grid(scene: Scene, *, constants=None, samples=None, ratio=None, levels="1", mailbox=False):
    """The grid ``calibrate predict`` recommends (analytic fidelity), built in the kernel:
    :func:`calibrate.predict.recommended_grid`.  levels : "auto" | "1" | "2" | "3".
    Returns (grid, description of the levels)."""
    from . import predict as _p

    grid, plan = _p.recommended_grid(scene, constants=constants, samples=samples, ratio=ratio, levels=levels,
                                     mailbox=mailbox)
    return grid, plan["level_plans"]


def camera_rays(scene: Scene, width: int, height: int, view=None):
    """The render's primary rays: one through each pixel centre, row-major from the top left.

    view : (3,) direction the camera looks along (default
    :data:`calibrate.rays.DEFAULT_VIEW_DIRECTION`), towards the box centre.
    Returns origins, directions, each (width * height, 3) float64 (unit directions).
    """
    from .rays import DEFAULT_VIEW_DIRECTION, camera_grid

    return camera_grid(scene.box_lo, scene.box_hi, _check_size(width, "width"), _check_size(height, "height"),
                       view_direction=DEFAULT_VIEW_DIRECTION if view is None else view)


def face_normals(scene: Scene) -> np.ndarray:
    """(F, 3) float64 unit normals of the scene's triangles (zero for a degenerate one)."""
    v = scene.vertices[scene.faces]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    length = np.linalg.norm(n, axis=1)
    out = np.zeros_like(n)
    good = length > 0
    out[good] = n[good] / length[good, None]
    return out


def shade(scene: Scene, prim: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(n, 3) float64 RGB in [0, 1]: ``|n . d|`` grey on a hit (prim >= 0), the background on a miss."""
    rgb = np.empty((prim.size, 3))
    rgb[:] = BACKGROUND_RGB
    hit = prim >= 0
    nrm = face_normals(scene)[prim[hit]]
    d = directions[hit] / np.linalg.norm(directions[hit], axis=1)[:, None]
    grey = SHADE_FLOOR + (1.0 - SHADE_FLOOR) * np.abs(np.einsum("ij,ij->i", nrm, d))
    rgb[hit] = grey[:, None]
    return rgb


def render(scene, *, width=DEFAULT_WIDTH, height=DEFAULT_HEIGHT, grid: Grid | None = None, resolution=None,
           levels="auto", constants=None, samples=None, ratio=None, view=None) -> dict:
    """Trace the default camera's primary rays through a grid; no file is written.

    Parameters
    ----------
    scene : :class:`Scene`, a built-in scene's name or a mesh file's path.
    width, height : image size in pixels; view : (3,) viewing direction (see :func:`camera_rays`).
    grid : a grid over ``scene`` to trace; else ``resolution`` (nx, ny, nz) builds a
        uniform one; else the recommendation of ``calibrate predict`` for ``levels``
        from ``constants``/``samples`` or ``ratio`` (see :func:`calibrate.predict.resolve_constants`).

    Returns
    -------
    dict with ``rgb`` (H, W, 3) float64 shaded image, ``hit`` (H, W) bool, ``prim``
    (H, W) int32 (-1 on a miss), ``steps``, ``tests``, ``subgrids`` (H, W) uint32 per-ray
    counts of the instrumented twin, ``grid`` (the Grid), ``levels`` (list of level dicts:
    resolution per level) and ``scene``.
    """
    if not isinstance(scene, Scene):
        scene = Scene.load(scene)
    width = _check_size(width, "width")
    height = _check_size(height, "height")
    levels_info = None
    if grid is None:
        if resolution is not None:
            grid = Grid.uniform(scene, tuple(resolution))
        else:
            grid, levels_info = recommended_grid(scene, constants=constants, samples=samples, ratio=ratio,
                                                 levels=levels)
    elif grid.scene is not scene:
        raise ValueError("the grid was built over another scene")
    if levels_info is None:
        levels_info = [dict(level=1, resolution=list(grid.resolution))]
        if grid.info["levels"] > 1:
            levels_info[0]["note"] = f"top of a {grid.info['levels']}-level grid"
    o, d = camera_rays(scene, width, height, view)
    t, prim, steps, tests, subgrids = grid.count(o, d, hits=True)
    shape = (height, width)
    return dict(scene=scene, grid=grid, levels=levels_info, rgb=shade(scene, prim, d).reshape(height, width, 3),
                hit=(prim >= 0).reshape(shape), prim=prim.reshape(shape), steps=steps.reshape(shape),
                tests=tests.reshape(shape), subgrids=subgrids.reshape(shape))


# ---------------------------------------------------------------------------------------
# PNG
# ---------------------------------------------------------------------------------------

def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def shaded_png(rgb: np.ndarray) -> bytes:
    """PNG bytes of an (H, W, 3) RGB image in [0, 1], exactly W x H pixels."""
    plt = _pyplot()
    buf = io.BytesIO()
    plt.imsave(buf, np.clip(rgb, 0.0, 1.0), format="png")
    return buf.getvalue()


def heatmap_png(values: np.ndarray, label: str, title: str | None = None) -> bytes:
    """PNG bytes of per-pixel counts (H, W) with a colour bar: (W + COLORBAR_STRIP_PIXELS) x H pixels."""
    from matplotlib.figure import Figure

    _pyplot()
    h, w = values.shape
    total_w = w + COLORBAR_STRIP_PIXELS
    fig = Figure(figsize=(total_w / HEATMAP_DPI, h / HEATMAP_DPI), dpi=HEATMAP_DPI)
    fig.patch.set_facecolor("white")
    ax = fig.add_axes((0.0, 0.0, w / total_w, 1.0))
    # a few extreme rays (e.g. through a cap's fan vertex) would darken everything else:
    # the scale ends at a high percentile and the bar's arrow marks the clipped values
    vmax = max(1.0, float(np.percentile(values, HEATMAP_SCALE_PERCENTILE)))
    clipped = float(values.max()) > vmax
    im = ax.imshow(values, cmap=HEATMAP_CMAP, vmin=0.0, vmax=vmax, interpolation="nearest", aspect="auto")
    ax.set_axis_off()
    # the bar: a narrow strip inside the right-hand margin, its labels beside it
    font = max(5.0, min(9.0, h / 40.0))
    bar_left = (w + 0.12 * COLORBAR_STRIP_PIXELS) / total_w
    cax = fig.add_axes((bar_left, 0.08, 0.14 * COLORBAR_STRIP_PIXELS / total_w, 0.84))
    bar = fig.colorbar(im, cax=cax, extend="max" if clipped else "neither")
    bar.ax.tick_params(labelsize=font, length=2, pad=1)
    bar.set_label(label, fontsize=font, labelpad=2)
    if title:
        ax.text(0.01, 0.01, title, transform=ax.transAxes, ha="left", va="bottom", color="white", fontsize=font)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=HEATMAP_DPI)
    return buf.getvalue()


def write_image(result: dict, out, heatmap: str | None = None) -> Path:
    """Write a :func:`render` result as a PNG (shaded, or a heatmap of ``steps``/``tests``)."""
    out = Path(out)
    _check_out(out)
    if heatmap is None:
        data = shaded_png(result["rgb"])
    else:
        if heatmap not in HEATMAPS:
            raise UserError(f"unknown heatmap {heatmap!r}; choose one of {', '.join(HEATMAPS)}")
        v = result[heatmap]
        title = f"{result['scene'].name}: mean {v.mean():.3g}, max {int(v.max())}"
        data = heatmap_png(v.astype(np.float64), HEATMAP_LABELS[heatmap], title)
    return atomic_write_bytes(out, data)


def _check_out(out: Path) -> None:
    if out.is_dir():
        raise UserError(f"cannot write {out}: it is a directory; give a file name")
    if out.suffix.lower() != ".png":
        raise UserError(f"cannot write {out}: the image is a PNG; give a file name ending in .png")
    check_writable(out)  # a read-only file or directory is reported before rendering


def summary(result: dict, out=None) -> dict:
    """The JSON-ready summary of a render: image path, resolution per level, counts per ray."""
    s, t = result["steps"], result["tests"]
    return dict(image=None if out is None else str(out), scene=result["scene"].name,
                triangles=result["scene"].n_triangles, width=int(s.shape[1]), height=int(s.shape[0]),
                levels=[dict(level=int(lv["level"]), resolution=[int(x) for x in lv["resolution"]])
                        for lv in result["levels"]],
                resolution=[int(x) for x in result["grid"].resolution],
                hit_fraction=float(result["hit"].mean()),
                steps_per_ray=dict(mean=float(s.mean()), max=int(s.max())),
                tests_per_ray=dict(mean=float(t.mean()), max=int(t.max())),
                subgrids_per_ray=dict(mean=float(result["subgrids"].mean()), max=int(result["subgrids"].max())))


# ---------------------------------------------------------------------------------------
# command line
# ---------------------------------------------------------------------------------------

def add_parser(sub):
    """Register the ``render`` verb on an argparse subparsers object; returns its parser."""
    from .predict import LEVEL_CHOICES, add_constants_options

    help_text = "render a scene through the grid: shaded, or a per-pixel heatmap of steps or tests per ray"
    sp = sub.add_parser("render", help=help_text, description=help_text)
    sp.add_argument("--json", action="store_true", help="machine-readable output on stdout")
    sp.add_argument("--quiet", action="store_true", help="no progress messages")
    sp.add_argument("mesh", nargs="?", default=DEFAULT_SCENE, metavar="MESH|SCENE",
                    help=f"a mesh file or a built-in scene's name (default {DEFAULT_SCENE})")
    sp.add_argument("--out", default="render.png", metavar="IMAGE.png", help="PNG to write (default render.png)")
    sp.add_argument("--heatmap", choices=HEATMAPS, help="per-pixel cost instead of the shaded image")
    res = sp.add_mutually_exclusive_group()
    res.add_argument("--resolution", nargs=3, type=int, metavar=("NX", "NY", "NZ"),
                     help="a uniform grid of this resolution (default: predict's recommendation)")
    res.add_argument("--levels", choices=LEVEL_CHOICES, default="auto",
                     help="levels of the recommended grid (default auto, as calibrate predict)")
    sp.add_argument("--width", type=int, default=DEFAULT_WIDTH, metavar="W", help=f"pixels (default {DEFAULT_WIDTH})")
    sp.add_argument("--height", type=int, default=DEFAULT_HEIGHT, metavar="H",
                    help=f"pixels (default {DEFAULT_HEIGHT})")
    sp.add_argument("--view", nargs=3, type=float, metavar=("DX", "DY", "DZ"),
                    help="direction the camera looks along, towards the box centre (up is +z)")
    add_constants_options(sp, "recommend the grid from your own T_int/T_step alone",
                          "calibration file (default ./calibration.json)")
    sp.set_defaults(func=cmd_render)
    return sp


def cmd_render(args) -> int:
    """Run the ``render`` verb."""
    import json

    from .predict import constants_from_args

    out = Path(args.out)
    _check_out(out)
    width = _check_size(args.width, "--width")
    height = _check_size(args.height, "--height")
    if args.view is not None:  # before loading the scene and planning its grid
        v = np.asarray(args.view, dtype=np.float64)
        if not (np.all(np.isfinite(v)) and np.any(v != 0)):
            raise UserError(f"--view must be a finite non-zero 3-vector DX DY DZ, got {' '.join(map(str, args.view))}")
    scene = Scene.load(args.mesh)
    src = {} if args.resolution is not None else constants_from_args(args, rays="camera")  # it traces camera rays
    if not args.quiet and not args.json and sys.stderr.isatty():
        print(f"rendering {scene.name} ({scene.n_triangles:,} triangles) at {width}x{height} ...", file=sys.stderr)
    result = render(scene, width=width, height=height, resolution=args.resolution, levels=args.levels,
                    view=args.view, **src)
    write_image(result, out, args.heatmap)
    info = summary(result, out)
    if args.json:
        sys.stdout.write(json.dumps(info, indent=2, allow_nan=False) + "\n")
        return 0
    res = " / ".join("x".join(str(x) for x in lv["resolution"]) for lv in info["levels"])
    print(f"{out}: {info['scene']} ({info['triangles']:,} triangles), {width}x{height}, grid {res}; "
          f"{100 * info['hit_fraction']:.0f}% of rays hit; steps per ray mean {info['steps_per_ray']['mean']:.3g} "
          f"max {info['steps_per_ray']['max']}, tests per ray mean {info['tests_per_ray']['mean']:.3g} "
          f"max {info['tests_per_ray']['max']}")
    return 0

