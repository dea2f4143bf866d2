"""`calibrate bench`: gridcal's recommended grids against Embree on the same rays, and how they scale.

Throughput (:func:`bench_scene`, the default verb)
    For each scene, the recommended uniform grid (``levels=1``) and the recommended
    nested grid (``levels=auto``; both from the analytic plan of
    :func:`calibrate.predict.recommended_grid`) trace the same rays as Embree through
    embreex (an optional extra: ``pip install 'gridcal[bench]'``) and, where it is
    installed, trimesh's own triangle ray module (``trimesh.ray.ray_triangle``, which
    needs rtree).  One core: the process is pinned before timing.

    Rays: ``isotropic`` (isotropic random lines through the scene's box, starting
    outside it), ``isotropic-wide`` (the same through a box three times larger about
    the same centre: a miss-heavy mix) and ``camera`` (pinhole primary rays framing the
    box).  Rays are rounded to float32 once (Embree's precision) and every contender
    traces those same rays; the mesh is given to Embree as float32, to gridcal as
    float64.

    How each contender is fed and timed: one call per batch of ``batch`` rays (16,384 by
    default), the same batch for all, timed around the Python call by the calling
    thread's CPU time (``time.thread_time_ns``; every contender traces in the calling
    thread, and the time it waits for a core on a busy host is left out) or, with
    ``clock="wall"``, by ``time.perf_counter_ns``; every contender pays its own
    per-call overhead once per batch.  gridcal: :meth:`calibrate._grid.Grid.timed_batch` (one pass of the C
    kernel over the batch).  Embree: ``EmbreeScene.run(origins, directions,
    query="INTERSECT")`` of embreex, which loops over the batch in compiled code calling
    Embree's single-ray ``rtcIntersect1`` once per ray (no packets or streams).
    trimesh: ``RayMeshIntersector.intersects_id(..., multiple_hits=False)`` on a smaller
    batch (it is vectorised numpy).  Repeats are interleaved (round r times every
    contender once, in a rotating order) after one untimed warm-up call each; the
    median and the spread (``(max - min) / median``) of the per-batch rates are
    reported; the ratio to Embree is the median over rounds of the two rates measured
    side by side in the same round (a slow spell of a shared host hits both).

    First-hit semantics: before timing, every contender's first hits on the rays are
    compared with gridcal's uniform grid (:func:`first_hit_agreement`): a ray agrees
    when both miss, or both hit at t within ``T_REL_TOL`` relative (Embree's float32
    mesh and arithmetic) on the same triangle, or on another triangle the ray also meets
    at that t (a tie at a shared edge or vertex, checked in float64).  At least
    ``MIN_AGREEMENT`` of the rays must agree; the fraction is printed.

Scale (:func:`scale_bench`, ``--scale``)
    The built-in bumpy sphere (:func:`calibrate.scenes.sphere_mesh`) from 10^3 up to
    ``max_triangles`` triangles (5 x 10^6 by default), plus any mesh files given: the
    time to predict and to build the recommended uniform grid, its references and
    memory, and traversal throughput (isotropic rays); the growth exponent of each
    (log-log least squares over the built-in series) is fitted by :func:`fit_exponent`.
"""

from __future__ import annotations

import importlib
import math
import sys
import time
from pathlib import Path

import numpy as np

from ._grid import Scene
from ._io import UserError

#: Rays per timed call (every contender, the same batch).
DEFAULT_BATCH = 16_384
#: Timed calls per contender and ray set, interleaved.
DEFAULT_REPEATS = 7
#: Rays per trimesh call (pure numpy: slow) and its timed calls.
TRIMESH_BATCH = 128
TRIMESH_REPEATS = 3
#: trimesh is skipped on scenes above this many triangles (its tree and memory).
TRIMESH_MAX_TRIANGLES = 200_000
#: First hits agree in t to this relative tolerance (Embree holds the mesh and rays in float32).
T_REL_TOL = 1e-4
#: Barycentric slack of the float64 check that a differing triangle is also met at that t (a tie).
TIE_BARY_TOL = 1e-4
#: Fraction of rays whose first hits must agree.
MIN_AGREEMENT = 0.999
#: The miss-heavy ray set traces lines through a box this many times the scene box (same centre).
WIDE_BOX_FACTOR = 3.0
RAY_SETS = ("isotropic", "isotropic-wide", "camera")
#: Scenes of ``calibrate bench`` with no arguments: compact, long-skinny, mixed.
DEFAULT_SCENES = ("sphere", "cylinder1996", "room")
#: Built-in ladder of ``--scale`` (triangle targets; the sphere has 20 f^2 of them).
SCALE_SIZES = (1_000, 10_000, 100_000, 1_000_000, 5_000_000)
DEFAULT_MAX_TRIANGLES = 5_000_000
#: Most triangles a grid can hold: the kernels' triangle indices are int32.
MAX_TRIANGLES = 2**31 - 1
SCALE_BATCH = 16_384
SCALE_REPEATS = 3
#: --scale builds the recommended nested grid up to this many triangles.
SCALE_NESTED_MAX_TRIANGLES = 1_100_000
SEED = 0
CONTENDERS = ("gridcal-uniform", "gridcal-nested", "embree", "trimesh")
#: Clocks of the timed calls: the calling thread's CPU time (default) or wall time.
CLOCKS = ("thread", "wall")


# ---------------------------------------------------------------------------------------
# optional contenders
# ---------------------------------------------------------------------------------------

def embree_unavailable() -> str | None:
    """None when embreex imports, else the reason (one sentence)."""
    try:
        importlib.import_module("embreex")
        importlib.import_module("embreex.rtcore_scene")
        importlib.import_module("embreex.mesh_construction")
    except ImportError as exc:
        return f"embreex is not importable ({exc}); install it with pip install 'gridcal[bench]'"
    return None


def trimesh_unavailable() -> str | None:
    """None when trimesh's triangle ray module can run (it needs rtree), else the reason."""
    try:
        importlib.import_module("rtree")
        importlib.import_module("trimesh.ray.ray_triangle")
    except ImportError as exc:
        return f"trimesh's ray module needs rtree, which is not importable ({exc}); pip install 'gridcal[bench]'"
    return None


class EmbreeTracer:
    """Embree 4 through embreex: a static scene of the mesh in float32."""

    api = "embreex EmbreeScene.run(query='INTERSECT'): rtcIntersect1 once per ray, in compiled code"

    def __init__(self, scene: Scene):
        reason = embree_unavailable()
        if reason:
            raise UserError(reason)
        rs = importlib.import_module("embreex.rtcore_scene")
        mc = importlib.import_module("embreex.mesh_construction")
        t0 = time.perf_counter()
        self._scene = rs.EmbreeScene()
        self._mesh = mc.TriangleMesh(self._scene, scene.vertices.astype(np.float32),
                                     scene.faces.astype(np.int32))
        # the first query commits the scene (builds the BVH)
        self._scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))
        self.build_s = time.perf_counter() - t0

    def first_hits(self, o32, d32):
        out = self._scene.run(o32, d32, output=1)
        prim = np.asarray(out["primID"], dtype=np.int64)
        prim[prim < 0] = -1
        t = np.where(prim >= 0, np.asarray(out["tfar"], dtype=np.float64), np.inf)
        return t, prim

    def call(self, o32, d32):
        return lambda: self._scene.run(o32, d32, query="INTERSECT")


class TrimeshTracer:
    """trimesh's own ray module (``trimesh.ray.ray_triangle``, numpy with an rtree of triangles)."""

    api = "trimesh.ray.ray_triangle.RayMeshIntersector.intersects_id(multiple_hits=False)"

    def __init__(self, scene: Scene):
        reason = trimesh_unavailable()
        if reason:
            raise UserError(reason)
        import trimesh
        from trimesh.ray.ray_triangle import RayMeshIntersector

        t0 = time.perf_counter()
        self._mesh = trimesh.Trimesh(scene.vertices, scene.faces, process=False)
        self._rt = RayMeshIntersector(self._mesh)
        _ = self._mesh.triangles_tree  # build the rtree now, not in the first timed call
        self.build_s = time.perf_counter() - t0

    def first_hits(self, o, d):
        tri, ray, loc = self._rt.intersects_id(o, d, multiple_hits=False, return_locations=True)
        tri, ray = np.asarray(tri, dtype=np.int64), np.asarray(ray, dtype=np.int64)
        loc = np.asarray(loc, dtype=np.float64).reshape(-1, 3)
        t = np.full(o.shape[0], np.inf)
        prim = np.full(o.shape[0], -1, dtype=np.int64)
        t[ray] = np.einsum("ij,ij->i", loc - o[ray], d[ray]) / np.einsum("ij,ij->i", d[ray], d[ray])
        prim[ray] = tri
        return t, prim

    def call(self, o, d):
        return lambda: self._rt.intersects_id(o, d, multiple_hits=False)


# ---------------------------------------------------------------------------------------
# rays and agreement
# ---------------------------------------------------------------------------------------

def make_rays(scene: Scene, kind: str, n: int, seed: int = SEED):
    """(origins, directions) float64, rounded to float32 once: the rays every contender traces."""
    from .rays import camera, isotropic

    lo, hi = np.asarray(scene.box_lo, float), np.asarray(scene.box_hi, float)
    if kind == "isotropic":
        o, d = isotropic(lo, hi, n, seed)
    elif kind == "isotropic-wide":
        c, h = 0.5 * (lo + hi), 0.5 * WIDE_BOX_FACTOR * (hi - lo)
        o, d = isotropic(c - h, c + h, n, seed)
    elif kind == "camera":
        o, d = camera(lo, hi, n, seed)
    else:
        raise UserError(f"unknown ray set {kind!r}; choose one of {', '.join(RAY_SETS)}")
    return o.astype(np.float32).astype(np.float64), d.astype(np.float32).astype(np.float64)


def _meets(vertices, faces, prim, o, d, t, tol):
    """Does ray i meet triangle prim[i] near t[i]?  Moller-Trumbore in float64 with slack ``tol``."""
    tri = vertices[faces[prim]]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 0
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = o - tri[:, 0]
    u = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, e1)
    v = np.einsum("ij,ij->i", d, q) * inv
    tt = np.einsum("ij,ij->i", e2, q) * inv
    return ok & (u >= -tol) & (v >= -tol) & (u + v <= 1 + tol) & (np.abs(tt - t) <= T_REL_TOL * np.abs(t))


def first_hit_agreement(t, prim, t_ref, prim_ref, scene: Scene | None = None, origins=None, directions=None,
                        rel_tol: float = T_REL_TOL) -> dict:
    """How far two tracers' first hits agree.

    A ray agrees when both miss, or both hit at t within ``rel_tol`` relative on the same
    triangle; with a different triangle at that t it is a tie (agrees) when ``scene`` and
    the rays are given and the ray meets both triangles at that t (float64 check), else it
    disagrees.  Returns a dict: ``rays``, ``agree`` (fraction), ``hit_miss`` (one hits,
    the other misses), ``t_differs``, ``triangle_differs``, ``ties``, ``hits`` (fraction
    of rays the reference hits), ``ok`` (agree >= MIN_AGREEMENT).
    """
    t = np.asarray(t, dtype=np.float64)
    t_ref = np.asarray(t_ref, dtype=np.float64)
    prim = np.asarray(prim, dtype=np.int64)
    prim_ref = np.asarray(prim_ref, dtype=np.int64)
    if not (t.shape == t_ref.shape == prim.shape == prim_ref.shape) or t.ndim != 1:
        raise ValueError(f"first hits differ in shape: {t.shape}, {prim.shape}, {t_ref.shape}, {prim_ref.shape}")
    hit, hit_ref = np.isfinite(t) & (prim >= 0), np.isfinite(t_ref) & (prim_ref >= 0)
    both = hit & hit_ref
    close = np.zeros(t.shape, dtype=bool)
    close[both] = np.abs(t[both] - t_ref[both]) <= rel_tol * np.maximum(np.abs(t[both]), np.abs(t_ref[both]))
    other = close & (prim != prim_ref)
    ties = np.zeros(t.shape, dtype=bool)
    if other.any() and scene is not None and origins is not None and directions is not None:
        i = np.flatnonzero(other)
        o, d = np.asarray(origins, float)[i], np.asarray(directions, float)[i]
        ties[i] = (_meets(scene.vertices, scene.faces, prim[i], o, d, t_ref[i], TIE_BARY_TOL)
                   & _meets(scene.vertices, scene.faces, prim_ref[i], o, d, t[i], TIE_BARY_TOL))
    agree = (~hit & ~hit_ref) | (close & (prim == prim_ref)) | ties
    n = int(t.size)
    frac = float(agree.mean()) if n else 1.0
    return dict(rays=n, agree=frac, hit_miss=int((hit != hit_ref).sum()), t_differs=int((both & ~close).sum()),
                triangle_differs=int((other & ~ties).sum()), ties=int(ties.sum()),
                hits=float(hit_ref.mean()) if n else 0.0, ok=bool(frac >= MIN_AGREEMENT))


# ---------------------------------------------------------------------------------------
# timing
# ---------------------------------------------------------------------------------------

def interleaved(calls: dict, repeats: int, warmups: int = 1, clock: str = "thread") -> dict:
    """Per name, ``repeats`` times (ns) of ``calls[name]()``, taken in interleaved rounds.

    Round r calls every contender once, starting at a rotating position, so a slow
    spell of the host touches all of them alike.  ``warmups`` untimed calls each first.
    clock: ``"thread"`` (the calling thread's CPU time: every contender traces in the
    calling thread, and time spent waiting for a core on a busy host is left out) or
    ``"wall"`` (``time.perf_counter_ns``).
    """
    if clock not in CLOCKS:
        raise ValueError(f"clock must be one of {', '.join(CLOCKS)}, got {clock!r}")
    names = list(calls)
    for _ in range(warmups):
        for name in names:
            calls[name]()
    out = {name: [] for name in names}
    read = time.thread_time_ns if clock == "thread" else time.perf_counter_ns
    for r in range(repeats):
        k = r % len(names) if names else 0
        for name in names[k:] + names[:k]:
            fn = calls[name]
            a = read()
            fn()
            out[name].append(max(read() - a, 1))
    return out


#: Bootstrap replicates of a throughput ratio's 95% interval, and their seed.
RATIO_BOOTSTRAP = 2000
RATIO_BOOTSTRAP_SEED = 7


def ratio_interval(rounds, replicates: int = RATIO_BOOTSTRAP, seed: int = RATIO_BOOTSTRAP_SEED) -> list:
    """Bootstrap 95% interval of a contender's throughput over Embree's, over ray sets.

    rounds : one (weight, embree_times, contender_times) per ray set, the two time lists
    paired by round (:func:`interleaved`); weight is Embree's median time on that set.  Each
    replicate draws every set's rounds again with replacement, takes the median of the
    paired ratios per set and combines the sets as ``bench_scene`` does (sum of weights over
    the sum of weight / ratio).  Returns [low, high]."""
    rng = np.random.default_rng(seed)
    sets = [(float(w), np.asarray(e, dtype=np.float64) / np.asarray(c, dtype=np.float64)) for w, e, c in rounds]
    draws = np.empty(int(replicates))
    for k in range(draws.size):
        num = den = 0.0
        for w, ratios in sets:
            r = float(np.median(ratios[rng.integers(0, ratios.size, ratios.size)]))
            num += w
            den += w / r
        draws[k] = num / den
    return [float(np.percentile(draws, 2.5)), float(np.percentile(draws, 97.5))]


def rate_summary(times_ns, rays: int) -> dict:
    """Median Mrays/s of per-batch times and the spread (max - min) / median of the rates."""
    rates = rays * 1e3 / np.asarray(times_ns, dtype=np.float64)
    med = float(np.median(rates))
    return dict(mrays_per_s=med, spread=float((rates.max() - rates.min()) / med), repeats=int(rates.size),
                min=float(rates.min()), max=float(rates.max()))


def fit_exponent(x, y) -> dict:
    """Least-squares fit of log y = log a + b log x: returns ``exponent`` b, ``prefactor`` a, ``r2``."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 1:
        raise ValueError(f"x and y must be 1-D of the same length, got {x.shape} and {y.shape}")
    if x.size < 2:
        raise ValueError(f"an exponent needs at least 2 points, got {x.size}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y)) and np.all(x > 0) and np.all(y > 0)):
        raise ValueError("an exponent fit needs finite positive x and y")
    lx, ly = np.log(x), np.log(y)
    if np.ptp(lx) == 0:
        raise ValueError("an exponent fit needs at least 2 distinct x")
    A = np.stack([np.ones_like(lx), lx], axis=1)
    (c, b), *_ = np.linalg.lstsq(A, ly, rcond=None)
    resid = ly - (c + b * lx)
    ss = float(((ly - ly.mean()) ** 2).sum())
    return dict(exponent=float(b), prefactor=float(math.exp(c)),
                r2=float(1.0 - (resid ** 2).sum() / ss) if ss > 0 else 1.0)


# ---------------------------------------------------------------------------------------
# throughput against Embree
# ---------------------------------------------------------------------------------------

def _check_int(value, name, lo):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < lo:
        raise UserError(f"{name} must be a whole number >= {lo}, got {value!r}")
    return int(value)


def bench_scene(scene, *, constants=None, samples=None, ratio=None, batch: int = DEFAULT_BATCH,
                repeats: int = DEFAULT_REPEATS, ray_sets=RAY_SETS, trimesh: bool = True, mailbox: bool = False,
                clock: str = "thread", progress=None) -> dict:
    """Throughput of gridcal's recommended grids, Embree and trimesh on one scene (module docstring).

    Returns a JSON-ready dict: ``scene``, ``triangles``, ``scene_class``, ``grids`` (per
    gridcal contender: levels, resolution, references, memory_bytes, predict_s,
    build_s), ``ray_sets`` (per set: hit fraction, per-contender rate summaries and
    agreement with gridcal's uniform grid, and ``ratio_vs_embree``: per contender the
    median over rounds of its rate over Embree's in the same round, and
    ``ratio_vs_embree_ci95``, its bootstrap 95% interval), ``mrays_per_s`` (per contender
    over all ray sets: total rays / total median time), ``ratio_vs_embree`` (the per-set
    paired ratios combined with weights of Embree's time per set) and
    ``ratio_vs_embree_ci95`` (:func:`ratio_interval`; not for trimesh, timed apart),
    ``skipped`` (contender -> reason), ``agreement_ok``.
    """
    from models.stats import scene_class

    from .predict import recommended_grid

    batch = _check_int(batch, "batch", 1)
    repeats = _check_int(repeats, "repeats", 1)
    for rs in ray_sets:
        if rs not in RAY_SETS:
            raise UserError(f"unknown ray set {rs!r}; choose one of {', '.join(RAY_SETS)}")
    if not isinstance(scene, Scene):
        scene = Scene.load(scene)
    note = progress or (lambda text: None)
    src = dict(constants=constants, samples=samples, ratio=ratio)
    grids, info = {}, {}
    for name, levels in (("gridcal-uniform", "1"), ("gridcal-nested", "auto")):
        note(f"{scene.name}: planning and building {name}")
        g, plan = recommended_grid(scene, levels=levels, mailbox=mailbox, **src)
        grids[name] = g
        gi = g.info
        info[name] = dict(levels=plan["levels"], resolution=plan["resolution"], predict_s=plan["predict_s"],
                          build_s=plan["build_s"], references=int(gi["n_refs"]),
                          memory_bytes=int(gi["memory_bytes"]), cells=int(gi["n_cells"]))
    skipped = {}
    tracers = {}
    reason = embree_unavailable()
    if reason:
        skipped["embree"] = reason
    else:
        note(f"{scene.name}: building Embree's scene")
        tracers["embree"] = EmbreeTracer(scene)
        info["embree"] = dict(build_s=tracers["embree"].build_s, api=EmbreeTracer.api)
    if trimesh:
        reason = trimesh_unavailable()
        if reason is None and scene.n_triangles > TRIMESH_MAX_TRIANGLES:
            reason = f"scene above {TRIMESH_MAX_TRIANGLES:,} triangles"
        if reason:
            skipped["trimesh"] = reason
        else:
            note(f"{scene.name}: building trimesh's ray tree")
            tracers["trimesh"] = TrimeshTracer(scene)
            info["trimesh"] = dict(build_s=tracers["trimesh"].build_s, api=TrimeshTracer.api)
    else:
        skipped["trimesh"] = "not requested (--no-trimesh)"
    sets = {}
    rounds_by_set = {}  # ray set -> (Embree's times, {contender: times}), paired by round
    agreement_ok = True
    for i, rs in enumerate(ray_sets):
        note(f"{scene.name}: {rs} rays")
        o, d = make_rays(scene, rs, batch, seed=SEED + i)
        o32, d32 = o.astype(np.float32), d.astype(np.float32)
        t_ref, prim_ref = grids["gridcal-uniform"].intersect(o, d)
        agreement = {}
        t, prim = grids["gridcal-nested"].intersect(o, d)
        agreement["gridcal-nested"] = first_hit_agreement(t, prim, t_ref, prim_ref, scene, o, d)
        calls = {name: (lambda run=g.timed_batch(o, d): run(1)) for name, g in grids.items()}
        if "embree" in tracers:
            t, prim = tracers["embree"].first_hits(o32, d32)
            agreement["embree"] = first_hit_agreement(t, prim, t_ref, prim_ref, scene, o, d)
            calls["embree"] = tracers["embree"].call(o32, d32)
        times = interleaved(calls, repeats, clock=clock)
        rates = {name: dict(rate_summary(ts, batch), rays=batch) for name, ts in times.items()}
        # per round, the contender's rate over Embree's, taken side by side: robust to a slow spell
        paired_rounds = {name: ts for name, ts in times.items() if name != "embree"} if "embree" in times else {}
        e = np.asarray(times.get("embree", ()), dtype=np.float64)
        paired = {name: float(np.median(e / np.asarray(ts, dtype=np.float64))) for name, ts in paired_rounds.items()}
        if "trimesh" in tracers:
            m = min(batch, TRIMESH_BATCH)
            t, prim = tracers["trimesh"].first_hits(o[:m], d[:m])
            agreement["trimesh"] = first_hit_agreement(t, prim, t_ref[:m], prim_ref[:m], scene, o[:m], d[:m])
            # the agreement call above was its warm-up
            ts = interleaved({"trimesh": tracers["trimesh"].call(o[:m], d[:m])}, TRIMESH_REPEATS, warmups=0,
                             clock=clock)["trimesh"]
            rates["trimesh"] = dict(rate_summary(ts, m), rays=m)
            if "embree" in rates:  # not paired: its own, smaller batch
                paired["trimesh"] = rates["trimesh"]["mrays_per_s"] / rates["embree"]["mrays_per_s"]
        agreement_ok &= all(a["ok"] for a in agreement.values())
        sets[rs] = dict(rays=batch, hits=float(np.isfinite(t_ref).mean()), rates=rates, agreement=agreement,
                        ratio_vs_embree=paired,
                        ratio_vs_embree_ci95={name: ratio_interval([(1.0, times["embree"], ts)])
                                              for name, ts in paired_rounds.items()})
        rounds_by_set[rs] = (times.get("embree"), paired_rounds)
    overall = {}
    for name in CONTENDERS:
        per = [s["rates"][name] for s in sets.values() if name in s["rates"]]
        if per:
            # total rays over total median time: each ray set weighs by its rays
            overall[name] = sum(p["rays"] for p in per) / sum(p["rays"] / p["mrays_per_s"] for p in per)
    ratio_vs = {}
    if "embree" in overall:
        # per ray set the paired ratio; over the sets weighted by Embree's time on each, so that
        # with equal ratios it is the ratio of total rays over total time (like mrays_per_s)
        for name in overall:
            if name == "embree":
                continue
            w = [(s["rays"] / s["rates"]["embree"]["mrays_per_s"], s["ratio_vs_embree"][name])
                 for s in sets.values() if name in s["ratio_vs_embree"]]
            ratio_vs[name] = sum(t for t, _ in w) / sum(t / r for t, r in w)
    ratio_ci = {}
    for name in ratio_vs:
        rounds = [(s["rays"] / s["rates"]["embree"]["mrays_per_s"], rounds_by_set[rs][0], rounds_by_set[rs][1][name])
                  for rs, s in sets.items() if name in rounds_by_set[rs][1]]
        if rounds:  # trimesh is timed on its own batch, not in Embree's rounds: no interval
            ratio_ci[name] = ratio_interval(rounds)
    cls = scene_class(scene.stats)
    return dict(scene=scene.name, triangles=scene.n_triangles, scene_class=cls[0] if isinstance(cls, tuple) else cls,
                grids=info, ray_sets=sets, mrays_per_s=overall, ratio_vs_embree=ratio_vs,
                ratio_vs_embree_ci95=ratio_ci, skipped=skipped,
                agreement_ok=bool(agreement_ok), batch=batch, repeats=repeats, clock=clock, t_rel_tol=T_REL_TOL,
                min_agreement=MIN_AGREEMENT)


# ---------------------------------------------------------------------------------------
# scale
# ---------------------------------------------------------------------------------------

def _scale_row(scene: Scene, *, src, batch, repeats, load_s, nested: bool, embree: bool, clock: str) -> dict:
    from .predict import recommended_grid

    grid, plan = recommended_grid(scene, levels="1", **src)
    gi = grid.info
    o, d = make_rays(scene, "isotropic", batch, seed=SEED)
    calls = {"gridcal-uniform": lambda run=grid.timed_batch(o, d): run(1)}
    refs = int(gi["n_refs"])
    row = dict(scene=scene.name, triangles=scene.n_triangles, resolution=plan["resolution"],
               load_s=load_s, predict_s=plan["predict_s"], build_s=plan["build_s"],
               predicted_and_built_s=plan["predict_s"] + plan["build_s"], references=refs,
               refs_per_s=refs / plan["build_s"] if plan["build_s"] > 0 else None,
               memory_bytes=int(gi["memory_bytes"]), bytes_per_triangle=gi["memory_bytes"] / scene.n_triangles)
    keep = [grid]
    if nested:
        ng, nplan = recommended_grid(scene, levels="auto", **src)
        ni = ng.info
        row["nested"] = dict(levels=nplan["levels"], resolution=nplan["resolution"], predict_s=nplan["predict_s"],
                             build_s=nplan["build_s"], references=int(ni["n_refs"]),
                             memory_bytes=int(ni["memory_bytes"]))
        calls["gridcal-nested"] = lambda run=ng.timed_batch(o, d): run(1)
        keep.append(ng)
    if embree:
        tracer = EmbreeTracer(scene)
        row["embree"] = dict(build_s=tracer.build_s)
        calls["embree"] = tracer.call(o.astype(np.float32), d.astype(np.float32))
        keep.append(tracer)
    times = interleaved(calls, repeats, clock=clock)
    rates = {name: rate_summary(ts, batch) for name, ts in times.items()}
    row["mrays_per_s"] = rates["gridcal-uniform"]["mrays_per_s"]
    row["spread"] = rates["gridcal-uniform"]["spread"]
    if nested:
        row["nested"]["mrays_per_s"] = rates["gridcal-nested"]["mrays_per_s"]
    if embree:
        row["embree"]["mrays_per_s"] = rates["embree"]["mrays_per_s"]
        e = np.asarray(times["embree"], dtype=np.float64)
        row["ratio_vs_embree"] = {name: float(np.median(e / np.asarray(ts, dtype=np.float64)))
                                  for name, ts in times.items() if name != "embree"}
    del keep, calls
    return row


def scale_bench(*, max_triangles: int = DEFAULT_MAX_TRIANGLES, sizes=SCALE_SIZES, meshes=(), constants=None,
                samples=None, ratio=None, batch: int = SCALE_BATCH, repeats: int = SCALE_REPEATS,
                nested_max_triangles: int = SCALE_NESTED_MAX_TRIANGLES, embree: bool = True,
                clock: str = "thread", progress=None) -> dict:
    """Build time, references, memory and throughput of the recommended uniform grid as N grows.

    The built-in bumpy sphere at each target of ``sizes`` up to ``max_triangles``, then
    each mesh of ``meshes`` (files or built-in names; not in the fits).  Up to
    ``nested_max_triangles`` the recommended nested grid is built and timed too (its plan
    and build take about 25 s at 10^6 triangles); Embree beside them when embreex imports
    and ``embree``.  Returns a dict with ``rows``, ``exponents`` (per quantity:
    :func:`fit_exponent` over the built-in series against the triangle count;
    ``ns_per_ray`` is 1000 / Mrays/s), ``largest`` and ``skipped``.
    """
    from .predict import recommended_grid
    from .scenes import sphere_mesh

    max_triangles = _check_int(max_triangles, "max triangles", 20)
    batch = _check_int(batch, "batch", 1)
    repeats = _check_int(repeats, "repeats", 1)
    note = progress or (lambda text: None)
    src = dict(constants=constants, samples=samples, ratio=ratio)
    skipped = {}
    if max_triangles > nested_max_triangles:
        skipped["gridcal-nested"] = f"above {nested_max_triangles:,} triangles (plan and build time, memory)"
    if embree and embree_unavailable():
        skipped["embree"] = embree_unavailable()
        embree = False
    opts = dict(src=src, batch=batch, repeats=repeats, embree=embree, clock=clock)
    loaded = []  # the meshes load first: a missing or corrupt one is reported before any measuring
    for spec in meshes:
        note(f"loading {spec}")
        t0 = time.perf_counter()
        loaded.append((Scene.load(spec), time.perf_counter() - t0))
    # one untimed plan and build first: the first call's imports are not the smallest scene's cost
    recommended_grid(Scene(*sphere_mesh(20)), levels="1", **src)
    targets = [n for n in sizes if n <= max_triangles]
    if not targets or targets[-1] < max_triangles:
        targets.append(max_triangles)
    rows = []
    for n in targets:
        note(f"sphere at {n:,} triangles")
        t0 = time.perf_counter()
        v, f = sphere_mesh(n)
        scene = Scene(v, f, name=f"sphere-{f.shape[0]}")
        load_s = time.perf_counter() - t0
        rows.append(dict(_scale_row(scene, load_s=load_s, nested=scene.n_triangles <= nested_max_triangles, **opts),
                         series="sphere"))
        del scene, v, f
    while loaded:
        scene, load_s = loaded.pop(0)
        note(f"{scene.name}")
        rows.append(dict(_scale_row(scene, load_s=load_s, nested=scene.n_triangles <= nested_max_triangles, **opts),
                         series="mesh"))
    series = [r for r in rows if r["series"] == "sphere"]
    exponents = {}
    if len({r["triangles"] for r in series}) >= 2:
        n = [r["triangles"] for r in series]
        for key, vals in (("build_s", [r["build_s"] for r in series]),
                          ("predict_s", [r["predict_s"] for r in series]),
                          ("references", [r["references"] for r in series]),
                          ("memory_bytes", [r["memory_bytes"] for r in series]),
                          ("ns_per_ray", [1e3 / r["mrays_per_s"] for r in series])):
            exponents[key] = fit_exponent(n, vals)
    largest = max(series, key=lambda r: r["triangles"]) if series else None
    if embree and len({r["triangles"] for r in series}) >= 2:
        n = [r["triangles"] for r in series]
        exponents["embree_ns_per_ray"] = fit_exponent(n, [1e3 / r["embree"]["mrays_per_s"] for r in series])
        exponents["embree_build_s"] = fit_exponent(n, [r["embree"]["build_s"] for r in series])
    return dict(rows=rows, exponents=exponents, batch=batch, repeats=repeats, clock=clock, skipped=skipped,
                largest=None if largest is None else dict(
                    triangles=largest["triangles"], predicted_and_built_s=largest["predicted_and_built_s"],
                    refs_per_s=largest["refs_per_s"], bytes_per_triangle=largest["bytes_per_triangle"]))


# ---------------------------------------------------------------------------------------
# command line
# ---------------------------------------------------------------------------------------

def add_parser(sub):
    """Register the ``bench`` verb on an argparse subparsers object; returns its parser."""
    from .cli import positive_number
    from .predict import add_constants_options

    help_text = ("single-core throughput of gridcal's recommended grids against Embree (and trimesh) on the same "
                 "rays; --scale: build time, references, memory and throughput as the triangle count grows")
    sp = sub.add_parser("bench", help=help_text, description=help_text)
    sp.add_argument("--json", action="store_true", help="machine-readable output on stdout")
    sp.add_argument("--quiet", action="store_true", help="no progress on stderr")
    sp.add_argument("meshes", nargs="*", metavar="MESH|SCENE",
                    help=f"mesh files or built-in scenes (default {' '.join(DEFAULT_SCENES)}; with --scale: extra "
                         "meshes beside the built-in sphere series)")
    add_constants_options(sp, "recommend grids from your own T_int/T_step",
                          "calibration file (default ./calibration.json when it exists, else --ratio 1)")
    sp.add_argument("--batch", type=int, default=None, metavar="N",
                    help=f"rays per timed call (default {DEFAULT_BATCH}; --scale {SCALE_BATCH})")
    sp.add_argument("--repeats", type=int, default=None, metavar="N",
                    help=f"interleaved timed calls per contender (default {DEFAULT_REPEATS}; --scale {SCALE_REPEATS})")
    sp.add_argument("--rays", default=",".join(RAY_SETS), metavar="SETS",
                    help=f"comma-separated ray sets (default {','.join(RAY_SETS)})")
    sp.add_argument("--no-trimesh", action="store_true", help="leave trimesh's ray module out")
    sp.add_argument("--mailbox", action="store_true",
                    help="gridcal's grids mailbox (each triangle tested once per ray)")
    sp.add_argument("--clock", default="thread", choices=CLOCKS,
                    help="time each call by the thread's CPU time (default: waiting for a core on a busy host is "
                         "left out) or by wall time")
    sp.add_argument("--fit", default="isotropic", choices=("isotropic", "camera", "pooled"),
                    help="whose constants of a calibration plan the grids: one ray set's alone (default isotropic: "
                         "the grids `calibrate predict` and `compare` recommend; a calibration without that fit "
                         "gives its pooled one) or the fit of every ray set together")
    sp.add_argument("--scale", action="store_true", help="the scaling benchmark instead")
    sp.add_argument("--max-triangles", type=positive_number("--max-triangles"), default=DEFAULT_MAX_TRIANGLES,
                    metavar="N", help=f"largest sphere of --scale (default {DEFAULT_MAX_TRIANGLES:g})")
    sp.set_defaults(func=cmd_bench)
    return sp


def _source(args) -> tuple[dict, str]:
    from .predict import DEFAULT_CALIBRATION, constants_from_args

    if args.ratio is None and not args.calibration and not Path(DEFAULT_CALIBRATION).exists():
        return dict(ratio=1.0), f"no calibration: ratio T_int/T_step = 1 assumed (./{DEFAULT_CALIBRATION} absent)"
    fit = getattr(args, "fit", "isotropic")
    src = constants_from_args(args, rays=None if fit == "pooled" else fit)
    if "ratio" in src:
        return src, f"ratio T_int/T_step = {src['ratio']:g} (given)"
    fitted_on = src["constants"].get("fitted_on")
    which = f", {fitted_on} rays' fit" if fitted_on else (", fit of every ray set" if fit == "pooled" else
                                                        f", fit of every ray set (it has no {fit} fit alone)")
    return src, f"calibration {args.calibration or DEFAULT_CALIBRATION}{which}"


def cmd_bench(args) -> int:
    import json

    from .protocol import pin_to_one_core

    src, source_note = _source(args)
    show = ((lambda text: print(text, file=sys.stderr, flush=True))
            if not args.quiet and sys.stderr.isatty() else None)
    for name in ("batch", "repeats"):
        v = getattr(args, name)
        if v is not None and v < 1:
            raise UserError(f"--{name} must be at least 1, got {v}")
    ray_sets = tuple(s.strip() for s in args.rays.split(",") if s.strip())
    if not ray_sets:
        raise UserError("--rays names no ray set")
    for rs in ray_sets:
        if rs not in RAY_SETS:
            raise UserError(f"unknown ray set {rs!r}; choose from {', '.join(RAY_SETS)}")
    if args.scale:
        if args.max_triangles != int(args.max_triangles):
            raise UserError(f"--max-triangles must be a whole number, got {args.max_triangles:g}")
        if args.max_triangles > MAX_TRIANGLES:
            raise UserError(f"--max-triangles must be at most {MAX_TRIANGLES:,} (the kernels number triangles "
                            f"in 32 bits), got {args.max_triangles:g}")
    with pin_to_one_core() as pin:
        if args.scale:
            result = scale_bench(max_triangles=int(args.max_triangles), meshes=tuple(args.meshes),
                                 batch=args.batch or SCALE_BATCH, repeats=args.repeats or SCALE_REPEATS,
                                 clock=args.clock, progress=show, **src)
        else:
            scenes = [Scene.load(m) for m in (args.meshes or DEFAULT_SCENES)]
            result = dict(scenes=[bench_scene(s, batch=args.batch or DEFAULT_BATCH,
                                              repeats=args.repeats or DEFAULT_REPEATS, ray_sets=ray_sets,
                                              trimesh=not args.no_trimesh, mailbox=args.mailbox,
                                              clock=args.clock, progress=show, **src) for s in scenes])
        result["pinning"] = pin.note
        result["clock"] = args.clock
    result["constants"] = source_note
    from ._kernels import traverse_isa

    result["kernel_isa"] = traverse_isa()
    from .predict import json_ready

    result = json_ready(result)
    if args.json:
        sys.stdout.write(json.dumps(result, indent=2, allow_nan=False) + "\n")
        return 0
    (_print_scale if args.scale else _print_bench)(result)
    return 0


def _print_bench(result: dict) -> None:
    from rich.table import Table

    from .cli import _console

    console = _console()
    for s in result["scenes"]:
        g = s["grids"]
        console.print(f"[bold]{s['scene']}[/bold]: {s['triangles']:,} triangles, {s['scene_class']}; "
                      + "; ".join(f"{n}: {v['levels']} level(s), top {'x'.join(map(str, v['resolution']))}, "
                                  f"{v['references']:,} refs, {v['memory_bytes'] / 2**20:.1f} MiB"
                                  for n, v in g.items() if n.startswith("gridcal")))
        table = Table(title=f"{s['scene']}: Mrays/s (median of {s['repeats']}, spread (max-min)/median; "
                            f"batches of {s['batch']:,} rays)")
        table.add_column("rays")
        table.add_column("hits", justify="right")
        names = [n for n in CONTENDERS if n in s["mrays_per_s"]]
        for n in names:
            table.add_column(n, justify="right")
        table.add_column("first hits agree with uniform", justify="left")
        for rs, v in s["ray_sets"].items():
            cells = []
            for n in names:
                r = v["rates"].get(n)
                cells.append("-" if r is None else f"{r['mrays_per_s']:.3g} ({100 * r['spread']:.0f}%)")
            agree = ", ".join(f"{n.replace('gridcal-', '')} {100 * a['agree']:.2f}%"
                              + ("" if a["ok"] else " [red]LOW[/red]")
                              + (f" ({a['ties']} ties)" if a["ties"] else "")
                              for n, a in v["agreement"].items())
            table.add_row(rs, f"{100 * v['hits']:.0f}%", *cells, agree)
        table.add_row("all", "", *[f"{s['mrays_per_s'][n]:.3g}" for n in names], "")
        console.print(table)
        if s["ratio_vs_embree"]:
            ci = s.get("ratio_vs_embree_ci95") or {}
            console.print("ratio vs Embree (bootstrap 95% interval over the paired rounds): " + ", ".join(
                (f"{n} {r:.2f}" if r >= 0.1 else f"{n} {r:.2g}")
                + (f" [{ci[n][0]:.2f}, {ci[n][1]:.2f}]" if n in ci else "")
                for n, r in s["ratio_vs_embree"].items()))
        for n, why in s["skipped"].items():
            console.print(f"skipped {n}: {why}")
        if not s["agreement_ok"]:
            _console(stderr=True).print(f"[yellow]warning:[/yellow] {s['scene']}: first hits agree on fewer than "
                                        f"{100 * s['min_agreement']:.1f}% of rays for some contender")
    console.print(f"first hits agree: both miss, or t within {T_REL_TOL:g} relative on the same triangle or a tie; "
                  f"needed on >= {100 * MIN_AGREEMENT:.1f}% of rays. Embree: {EmbreeTracer.api}. "
                  f"{result['constants']}; {result['pinning']}; clock {result['clock']}; "
                  f"gridcal's triangle tests on {result['kernel_isa']}")


def _print_scale(result: dict) -> None:
    out = sys.stdout
    cols = ("scene", "triangles", "predict s", "build s", "refs", "Mrefs/s", "MiB", "B/tri", "Mrays/s",
            "nested", "L", "Embree", "E build s")
    rows = []
    for r in result["rows"]:
        nested, embree = r.get("nested"), r.get("embree")
        rows.append((r["scene"], f"{r['triangles']:,}", f"{r['predict_s']:.3g}", f"{r['build_s']:.3g}",
                     f"{r['references']:,}", "-" if r["refs_per_s"] is None else f"{r['refs_per_s'] / 1e6:.3g}",
                     f"{r['memory_bytes'] / 2**20:.1f}", f"{r['bytes_per_triangle']:.0f}", f"{r['mrays_per_s']:.3g}",
                     "-" if nested is None else f"{nested['mrays_per_s']:.3g}",
                     "-" if nested is None else str(nested["levels"]),
                     "-" if embree is None else f"{embree['mrays_per_s']:.3g}",
                     "-" if embree is None else f"{embree['build_s']:.3g}"))
    widths = [max(len(c), *(len(row[i]) for row in rows)) for i, c in enumerate(cols)]
    out.write(f"recommended uniform grid as N grows: isotropic rays, batches of {result['batch']:,}, median of "
              f"{result['repeats']}; Mrays/s of the nested grid (L levels) and Embree beside it\n")
    fmt = lambda cells: "  ".join(c.ljust(w) if i == 0 else c.rjust(w)  # noqa: E731
                                  for i, (c, w) in enumerate(zip(cells, widths)))
    out.write(fmt(cols) + "\n")
    for row in rows:
        out.write(fmt(row) + "\n")
    for key, e in result["exponents"].items():
        out.write(f"{key} ~ N^{e['exponent']:.3f} (R^2 {e['r2']:.3f})\n")
    lg = result.get("largest")
    if lg:
        out.write(f"{lg['triangles']:,} triangles predicted and built in {lg['predicted_and_built_s']:.2f} s "
                  f"({lg['refs_per_s'] / 1e6:.3g} M references/s, {lg['bytes_per_triangle']:.0f} bytes per "
                  "triangle)\n")
    for n, why in result.get("skipped", {}).items():
        out.write(f"skipped {n}: {why}\n")
    out.write(f"{result['constants']}; {result['pinning']}; clock {result['clock']}; "
              f"gridcal's triangle tests on {result['kernel_isa']}\n")
