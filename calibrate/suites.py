"""The microbenchmark suites: configurations to time, with their exact counts.

A configuration is one grid and one batch of rays.  Its counts (rays, cells
stepped, triangle tests, subgrids entered; batch totals) come from the
instrumented twin on exactly the rays the timed twin will trace; its time
comes later from :func:`calibrate.protocol.measure`.

Isolating suites (first estimates, reported beside the in-context fit):
- ``empty``: grids with no triangles, m x m x m for growing m: T_setup and T_step;
- ``cell``: one cell holding k triangles, rays that miss them and rays aimed
  at them: T_int;
- ``subgrid``: the same top grid with and without a 1x1x1 subgrid in every
  cell: T_sub.

In-context suite: real traversals of built-in scenes at resolutions from
coarse to fine (uniform, and nested of depth 2 and 3) under isotropic and
camera rays, and of each of those scenes in a box twice its size (uniform
grids only; :func:`padded_scene`).  The exported constants come from fitting
this suite.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ._grid import Grid, Scene, _is_real, empty_grid, resolution_for_cells
from .protocol import Copies
from .rays import camera, isotropic
from .scenes import load_builtin, scattered_compact

#: Clock every configuration is timed with (see :meth:`Grid.timed_batch`): the timing
#: thread's CPU time, so a value leaves out the time the thread waited for a core.
#: On a shared host that wait is most of the noise; the cost of the work itself
#: (cache and memory stalls included) is what the constants describe.
TIMING_CLOCK = "thread"
#: Rays per batch in the isolating suites, whose grids and triangles stay in cache by design.
RAYS_PER_BATCH = 2048
#: Distinct rays per batch in the in-context suite.  A value traces its batch again and again
#: (as many loops as last ``calibrate.run.MIN_VALUE_NS``), so a short batch keeps what its own
#: rays touch cached from one loop to the next, which no stream of new rays does: on this
#: project's 2-core EPYC host (1 MiB L2, 32 MiB L3) the same grid took 202 ns a ray with 2,048
#: rays and 243-245 with 16,384-65,536 (`cylinder1996` 19x19x93, 8.7 MiB), 301 against 356-357
#: (the sphere at 55x54x55, 10 MiB), 1,135 against 1,325-1,340 (`cylinder19996` at 43x43x214,
#: 187 MiB).  At 16,384 the batch's footprint is well past that L3 and the time per ray is the
#: stream's; ``compare``'s and ``bench``'s batches are as long.
CONTEXT_RAYS_PER_BATCH = 16384
#: Empty-grid resolutions (cells per axis) of the isolating step suite; at most 40^3
#: cells (500 KiB, a quarter of this host's level-2 cache), so the cells stay in cache
#: and T_step is the step itself (48^3 already costs 4% more a step here).  The
#: isolated fit uses the sides whose rays walk in the steady state (at least
#: ``calibrate.run.STEADY_STEPS_PER_RAY`` steps); the short walks show the transient.
EMPTY_GRID_SIDES = (1, 2, 4, 8, 12, 16, 20, 24, 28, 32, 36, 40)
#: Triangles in the single cell of the isolating intersection suite: the first k of one
#: set of scattered triangles, so every list holds triangles of the same size and a
#: test's outcome (hence its cost) is drawn from the same mix whatever k.  The isolated
#: fit uses the lists of at least ``calibrate.run.STEADY_TESTS_PER_RAY`` triangles.
CELL_TRIANGLE_COUNTS = (1, 16, 32, 48, 64, 96, 128, 160, 192, 224, 256)
#: Top-level sides of the isolating subgrid suite.
SUBGRID_SIDES = (2, 4, 8, 16)
#: The in-context suite's built-in scenes.
BARE_CONTEXT_SCENES = ("sphere", "cylinder1996", "scattered-compact", "scattered-skinny", "cylinder196")
#: Each of them also padded: the scene in a box :data:`PADDED_SCALE` times its own per axis
#: (:func:`padded_scene`), named with :data:`PADDED_SUFFIX`, so a ray crosses empty cells
#: before and after the scene's.  In a bare scene a grid's steps, occupied cells entered and
#: bytes read grow together with its resolution, which leaves T_step on a ridge with T_visit
#: and T_mem (r's posterior correlation with T_step -0.8 to -0.9); in a padded one steps grow
#: apart from the other two.  On this project's 2-core host the padded sphere alone took r's
#: 95% half-width from 19-26% to 10-15% (isotropic rays) and from 7-9% to 5-6% (camera); all
#: five padded, to 5.7-7.3% and 2.2-3.3%, with the cross-validated error at 1.6-2.1% against
#: 2.3-2.5% (docs/calibration.md, "Empty space around the scenes").
PADDED_SCALE = 2.0
PADDED_SUFFIX = "-padded"
#: Scenes of the in-context suite: the built-in ones, then each padded.  Padded scenes are
#: timed with uniform grids only: the padded sphere's nested grids were priced 24-52% over
#: their time (likely one T_sub for subgrids of another kind), which widened every
#: configuration's misfit term.
CONTEXT_SCENES = BARE_CONTEXT_SCENES + tuple(name + PADDED_SUFFIX for name in BARE_CONTEXT_SCENES)
#: Total cells as multiples of N for the in-context uniform grids (coarse to fine).  Dense
#: (about half an octave apart): the width of r's interval is set by how the model misfits
#: the configurations, not by the repeats, and shrinks with the number of configurations; on
#: this project's 2-core host, 154 in-context configurations of about 5 values each (these
#: and the skinny extras below) took r's 95% half-width from 13-17% to 5-9% (camera rays)
#: and from 28-36% to 19-24% (isotropic) against 92 of 9-10 values each (the coarse
#: resolutions below), in the same 51-60 s (docs/calibration.md, "More resolutions, fewer repeats").
CONTEXT_CELLS_PER_TRIANGLE = (1 / 8, 1 / 4, 1 / 2, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0)
#: Extra, finer multiples for scenes of long skinny triangles, whose optimum is O(N^1.5) cells.
CONTEXT_SKINNY_EXTRA = (12.0, 16.0, 24.0, 32.0)
#: The coarser resolutions of before (an octave apart), for the quick suites of the tests and of
#: ``calibrate tradeoff --quick``, where fewer configurations keep them short.
COARSE_CONTEXT_CELLS_PER_TRIANGLE = (1 / 8, 1 / 2, 1.0, 2.0, 4.0, 8.0)
COARSE_CONTEXT_SKINNY_EXTRA = (16.0, 32.0)
#: Nesting depths of the in-context nested grids.
CONTEXT_LEVELS = (2, 3)
#: Ray sets of the in-context suite.
CONTEXT_RAY_SETS = ("isotropic", "camera")
#: Camera rays drawn per ray kept (those missing the grid box are dropped).
CAMERA_SURPLUS = 8
#: Copies of each in-context grid, built one after another, its values cycling through
#: them (:class:`calibrate.protocol.Copies`): where a grid lies in memory moves its
#: time by a few per cent, the same for every value of one copy.
CONTEXT_COPIES = 3
#: Cap on a configuration's cells, so no suite grid strains memory.
MAX_SUITE_CELLS = 4_000_000


@dataclass
class Config:
    """One timed configuration: a grid, a batch of rays, and the batch's exact counts."""

    name: str
    kind: str  # "isolated" or "in_context"
    suite: str  # "empty", "cell", "subgrid" or "context"
    scene: str
    resolution: str
    intersector: str
    rays: int
    steps: int
    tests: int
    subgrids: int
    run: Callable = field(repr=False)
    ray_set: str = ""
    memory_bytes: int = 0
    visits: int = 0
    hits: int = 0
    changes: int = 0

    def record(self) -> dict:
        """The JSON record of this configuration (without timings)."""
        return dict(name=self.name, kind=self.kind, suite=self.suite, scene=self.scene,
                    resolution=self.resolution, intersector=self.intersector, ray_set=self.ray_set,
                    rays=int(self.rays), steps=int(self.steps), tests=int(self.tests),
                    subgrids=int(self.subgrids), memory_bytes=int(self.memory_bytes),
                    visits=int(self.visits), hits=int(self.hits), changes=int(self.changes))


def _res_label(res) -> str:
    return "x".join(str(int(x)) for x in res)


def _config(name, kind, suite, scene_name, res_label, intersector, grid: Grid, o, d, ray_set,
            copies=()) -> Config:
    """The configuration of ``grid`` on rays (o, d); ``copies``: more builds of the same grid,
    timed in turn with it (:class:`calibrate.protocol.Copies`)."""
    t, _, steps, tests, subgrids, visits, changes = grid.count(o, d, hits=True, visits=True, changes=True)  # one walk
    runs = [g.timed_batch(o, d, clock=TIMING_CLOCK) for g in (grid, *copies)]
    return Config(name=name, kind=kind, suite=suite, scene=scene_name, resolution=res_label,
                  intersector=intersector, rays=int(o.shape[0]), steps=int(steps.sum(dtype=np.int64)),
                  tests=int(tests.sum(dtype=np.int64)), subgrids=int(subgrids.sum(dtype=np.int64)),
                  run=runs[0] if len(runs) == 1 else Copies(runs), ray_set=ray_set,
                  memory_bytes=int(grid.info["memory_bytes"]), visits=int(visits.sum(dtype=np.int64)),
                  hits=int(np.count_nonzero(np.isfinite(t))), changes=int(changes.sum(dtype=np.int64)))


def isolated_configs(intersector: str, seed: int = 0) -> list[Config]:
    """The isolating suites for one intersector (deterministic given the seed)."""
    out = []
    lo, hi = np.zeros(3), np.ones(3)
    o, d = isotropic(lo, hi, RAYS_PER_BATCH, seed)
    for m in EMPTY_GRID_SIDES:
        g = empty_grid(lo, hi, (m, m, m), intersector)
        out.append(_config(f"empty {m}^3", "isolated", "empty", "empty", _res_label((m, m, m)), intersector,
                           g, o, d, "isotropic"))
    # one cell, k small triangles (the first k of one scattered set, all of one size);
    # isotropic rays mostly miss them, aimed rays hit one
    pool_v, pool_f = scattered_compact(max(CELL_TRIANGLE_COUNTS), seed=seed + 7)
    for k in CELL_TRIANGLE_COUNTS:
        v, f = pool_v[: 3 * k], pool_f[:k]
        scene = Scene(v, f, name=f"cell {k}")
        g = Grid.uniform(scene, (1, 1, 1), intersector)
        oi, di = isotropic(scene.box_lo, scene.box_hi, RAYS_PER_BATCH, seed + 1)
        out.append(_config(f"cell k={k} miss", "isolated", "cell", scene.name, "1x1x1", intersector, g, oi, di,
                           "isotropic"))
        centroids = v[f].mean(axis=1)
        rng = np.random.default_rng(seed + 11 + k)
        target = centroids[rng.integers(0, k, RAYS_PER_BATCH)]
        oh, _ = isotropic(scene.box_lo, scene.box_hi, RAYS_PER_BATCH, seed + 2)
        dh = target - oh
        dh /= np.linalg.norm(dh, axis=1, keepdims=True)
        out.append(_config(f"cell k={k} hit", "isolated", "cell", scene.name, "1x1x1", intersector, g, oh, dh,
                           "aimed"))
    # the same top grid without and with a 1x1x1 subgrid in every cell
    v, f = scattered_compact(64, seed=seed + 3)
    scene = Scene(v, f, name="subgrid probe")
    os_, ds = isotropic(scene.box_lo, scene.box_hi, RAYS_PER_BATCH, seed + 4)
    for m in SUBGRID_SIDES:
        res = (m, m, m)
        plain = Grid.uniform(scene, res, intersector)
        out.append(_config(f"subgrid {m}^3 none", "isolated", "subgrid", scene.name, _res_label(res), intersector,
                           plain, os_, ds, "isotropic"))
        ones = np.ones((m ** 3, 3), dtype=np.int32)
        nested = Grid.nested(scene, levels=2, resolution=res, subgrid_resolutions=ones, intersector=intersector)
        out.append(_config(f"subgrid {m}^3 all", "isolated", "subgrid", scene.name,
                           _res_label(res) + " / 1x1x1", intersector, nested, os_, ds, "isotropic"))
    return out


def padded_scene(name: str, scale: float = PADDED_SCALE) -> Scene:
    """Built-in scene ``name`` with its box grown ``scale`` times per axis about its centre.

    Two triangles of a thousandth of the box's largest half-side, each in a corner of the
    grown box, set the box (a grid's box is its scene's); the rest of the added space is
    empty.  Named ``name`` + :data:`PADDED_SUFFIX`.
    """
    if not (_is_real(scale) and math.isfinite(float(scale)) and float(scale) >= 1.0):
        raise ValueError(f"scale must be finite and >= 1, got {scale!r}")
    v, f = load_builtin(name)
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    eps = 1e-3 * float(half.max())
    extra = []
    for sign in (-1.0, 1.0):
        corner = centre + sign * scale * half
        # the other two vertices step inwards, so the corner is the box's
        extra.append([corner, corner - sign * np.array([eps, 0.0, 0.0]), corner - sign * np.array([0.0, eps, 0.0])])
    verts = np.vstack([v, np.asarray(extra, dtype=np.float64).reshape(-1, 3)])
    faces = np.vstack([f, len(v) + np.arange(6, dtype=np.int64).reshape(2, 3)])
    return Scene(np.ascontiguousarray(verts), np.ascontiguousarray(faces), name=name + PADDED_SUFFIX)


def context_scene(name: str) -> Scene:
    """An in-context scene by name: a built-in scene, or one with :data:`PADDED_SUFFIX` padded."""
    if name.endswith(PADDED_SUFFIX):
        return padded_scene(name[: -len(PADDED_SUFFIX)])
    return Scene.builtin(name)


def hits_box(o: np.ndarray, d: np.ndarray, lo, hi) -> np.ndarray:
    """(n,) bool: which rays (t >= 0) meet the box [lo, hi] (slab test, numpy)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (np.asarray(lo) - o) * inv
        t2 = (np.asarray(hi) - o) * inv
    tn = np.nanmax(np.minimum(t1, t2), axis=1)
    tf = np.nanmin(np.maximum(t1, t2), axis=1)
    return (tf >= np.maximum(tn, 0.0))


def _rays(scene: Scene, ray_set: str, seed: int):
    """A batch of :data:`CONTEXT_RAYS_PER_BATCH` rays that all enter the grid, as the cost model assumes.

    Isotropic lines through the box all do by construction; a camera framing
    the box's bounding sphere also sees past an elongated box, so its rays are
    drawn in surplus and those missing the box are dropped."""
    n = CONTEXT_RAYS_PER_BATCH
    if ray_set == "isotropic":
        return isotropic(scene.box_lo, scene.box_hi, n, seed)
    if ray_set == "camera":
        o, d = camera(scene.box_lo, scene.box_hi, CAMERA_SURPLUS * n, seed)
        keep = hits_box(o, d, scene.box_lo, scene.box_hi)
        return o[keep][:n], d[keep][:n]
    raise ValueError(f"unknown ray set {ray_set!r}")


def context_configs(intersector: str, seed: int = 0, scenes=None, copies: int | None = None) -> list[Config]:
    """The in-context suite: built-in scenes (default CONTEXT_SCENES) x resolutions x ray sets,
    each grid built ``copies`` times (default :data:`CONTEXT_COPIES`)."""
    copies = CONTEXT_COPIES if copies is None else copies
    if isinstance(copies, bool) or int(copies) < 1:
        raise ValueError(f"copies must be >= 1, got {copies!r}")
    scenes = CONTEXT_SCENES if scenes is None else scenes
    out = []
    for si, name in enumerate(scenes):
        scene = context_scene(name)
        ext = scene.box_hi - scene.box_lo
        n = scene.n_triangles
        multiples = list(CONTEXT_CELLS_PER_TRIANGLE)
        if name.startswith("cylinder") or name == "scattered-skinny":
            multiples += list(CONTEXT_SKINNY_EXTRA)
        grids = []
        for c in multiples:
            res = resolution_for_cells(min(c * n, MAX_SUITE_CELLS), ext)
            grids.append((_res_label(res), lambda res=res, scene=scene: Grid.uniform(scene, res, intersector)))
        for levels in () if name.endswith(PADDED_SUFFIX) else CONTEXT_LEVELS:
            grids.append((f"L{levels}", lambda levels=levels, scene=scene: Grid.nested(
                scene, levels=levels, intersector=intersector)))
        # Each grid and its copies are built once and timed under every ray set: in each ray
        # set's own fit no two configurations share a grid (in the pooled fit, where a copy lies
        # in memory now moves both ray sets' values of it alike, a few per cent averaged over
        # its copies); the builds were two thirds of this suite's set-up time when each ray set
        # built its own.
        built = []
        for label, build in grids:
            grid = build()
            if label.startswith("L"):
                label = f"{label} {_res_label(grid.resolution)}"
            built.append((label, grid, [build() for _ in range(int(copies) - 1)]))
        for ri, ray_set in enumerate(CONTEXT_RAY_SETS):
            o, d = _rays(scene, ray_set, seed + 100 * si + ri)
            for label, grid, more in built:
                out.append(_config(f"{name} {label} {ray_set}", "in_context", "context", name, label, intersector,
                                   grid, o, d, ray_set, copies=more))
    return out


def design(configs: list[Config], timings: dict) -> dict:
    """The fit's design from configurations and their Measurements (name -> Measurement)."""
    have = [c for c in configs if c.name in timings and timings[c.name].values_ns]
    return dict(
        rays=np.array([c.rays for c in have], dtype=np.float64),
        steps=np.array([c.steps for c in have], dtype=np.float64),
        tests=np.array([c.tests for c in have], dtype=np.float64),
        subgrids=np.array([c.subgrids for c in have], dtype=np.float64),
        times_ns=[np.asarray(timings[c.name].values_ns, dtype=np.float64) for c in have],
    ), have


def expected_seconds(n_configs: int, rounds: int, min_value_ns: float, warmups: int) -> float:
    """Rough measuring time: loop calibration (~2 values) + warm-ups + rounds, per configuration."""
    return n_configs * (2 + warmups + rounds) * min_value_ns * 1e-9 * 1.3


def fmt_ns(x: float) -> str:
    return f"{x:.3g}" if math.isfinite(x) else "nan"
