"""Effects (DESIGN §3.3): which terms a scene calls for, each with a reason and a number.

An effect is kept only when removing it changes the predicted ns per ray at the
optimum by more than ``EFFECT_TOLERANCE`` (relative).  The procedure:

1. optimum of the full model (every applicable term on);
2. for each effect, the predicted time at that same resolution with the effect
   removed; relative change ``|T_without - T_full| / T_full``;
3. the selected model keeps the effects above tolerance and is re-optimised.

Effects: ``edge`` (E1 terms), ``area`` (E2 terms), ``mailbox`` (tests once per ray
per triangle; only when the kernel mailboxes), ``termination`` (rays stop at the
first hit; where they stop sampled on the real mesh, or an approximate analytic model,
see :func:`termination_fraction`),
``clustering`` (non-uniform density; see :func:`clustering_index`), ``subgrid``
(T_sub per subgrid entered; nested grids only).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .general import Terms, optimal_uniform, predict_uniform
from .stats import SceneStats

#: An effect is used when removing it changes predicted time at the optimum by more
#: than this fraction.
EFFECT_TOLERANCE = 0.02


@dataclass(frozen=True)
class Effect:
    """name; used; change = relative change of predicted time when removed; reason."""

    name: str
    used: bool
    change: float
    reason: str


@dataclass(frozen=True)
class EffectSelection:
    """Selected terms, the resolution they give, and every effect's verdict."""

    terms: Terms
    resolution: tuple
    ns_per_ray: float
    effects: list


def rays_stop_on_entry(stats: SceneStats) -> bool:
    """The sampled rays (:attr:`SceneStats.termination`) stop where they enter the box.

    True when the chord they cover before their first hits, summed, is less than one
    ray's chord: the traversed fraction is below what the sample resolves (the room:
    its walls are the box's faces).  The count model then has no finite optimum: a ray
    enters one cell and tests its triangles, so its time falls with the cell size all
    the way to the largest grid, and what bounds a real grid there (the memory a finer
    grid takes, the triangles a ray's first cell holds however small it is) is not in
    the counts.  :func:`termination_fraction` then counts without termination.
    """
    ts = stats.termination
    return ts is not None and ts.fraction * ts.rays < 1.0


def termination_fraction(stats: SceneStats) -> tuple[float, float]:
    """Fraction of the no-termination work a ray does when it stops at its first hit.

    SAMPLED when ``stats.termination`` holds a :class:`models.stats.TerminationSample`
    (``calibrate.predict`` traces isotropic lines through the real mesh): its fraction and
    hit probability, as measured; when they stop where they enter
    (:func:`rays_stop_on_entry`), ``(1.0, p_hit)``: counted without termination.

    Otherwise APPROXIMATE (flagged as such wherever it is reported):
    - hit probability ``p``: for a closed (watertight) surface of area A,
      ``p = min(1, A / S)`` -- exact for a convex surface (Crofton), an over-estimate
      otherwise (a line may cross a non-convex surface 4+ times); for an open mesh
      ``p = min(1, 2A / S)`` (each side of a flat piece counts; exact for pieces that
      do not overlap in any line's view).
    - a ray that hits covers, on average, half of the box chord outside the object:
      fraction ``(1 - c) / 2`` with ``c`` = mean chord in the object / mean chord in
      the box = ``(4 V_in / A) / (4 V / S)`` (Cauchy's mean chord), clipped to [0, 1]
      (0 for open meshes).  Exact when the object is convex and centred.
    Work is assumed proportional to the distance traversed (steps and tests alike),
    so the fraction is ``(1 - p) + p (1 - c) / 2``.  Measured against sampled rays
    (docs/compare.md, "Where rays stop, sampled"), it is far off for a mesh that
    encloses the box (Sponza: 0.50 against 0.02) and for open meshes generally.

    Returns
    -------
    (fraction, p_hit) : both in [0, 1]; fraction > 0.
    """
    if stats.termination is not None:
        ts = stats.termination
        return (1.0 if rays_stop_on_entry(stats) else max(ts.fraction, 1e-6)), ts.p_hit
    a = stats.area
    s = stats.surface
    if stats.watertight:
        p = min(1.0, a / s)
        c = min(1.0, (stats.enclosed_volume * s) / (a * stats.volume)) if a > 0 else 0.0
    else:
        p = min(1.0, 2.0 * a / s)
        c = 0.0
    frac = (1.0 - p) + p * (1.0 - c) / 2.0
    return max(frac, 1e-6), p


def clustering_index(cell_counts) -> float:
    """Dispersion of per-cell reference counts, ``var / mean`` (1 for a Poisson/uniform scene).

    cell_counts : (C,) counts of every cell of a grid (empty cells included).
    """
    c = np.asarray(cell_counts, dtype=np.float64)
    if c.ndim != 1 or c.size == 0:
        raise ValueError("cell_counts must be a non-empty 1-D array")
    m = c.mean()
    return float(c.var() / m) if m > 0 else 0.0


def _pct(x):
    return f"{100.0 * x:.1f}%"


def select_effects(stats: SceneStats, t_setup, t_step, t_int, *, mailbox=False, termination=True,
                   overlap="exact", tolerance=EFFECT_TOLERANCE, dispersion=None, levels=1,
                   subgrid_ns=0.0, clustering_change=None) -> EffectSelection:
    """Decide which effects matter for this scene at its optimum.

    Parameters
    ----------
    stats : SceneStats.
    t_setup, t_step, t_int : ns (calibrated constants or a ratio scaled to ns).
    mailbox : the kernel mailboxes (otherwise the mailbox effect is reported, not used).
    termination : rays stop at the first hit (False: shadow-less counting as in the talk).
    overlap : "exact" or "bbox" triangle-to-cell assignment of the kernel.
    tolerance : relative change above which an effect is used.
    dispersion : optional :func:`clustering_index` at the candidate resolution.
    levels : grid depth of the prediction; ``subgrid_ns`` its T_sub * subgrids per ray
        and ``clustering_change`` the relative change of the nested prediction when each
        subgrid gets the mean sub-scene instead of its own (from :mod:`models.nested`).

    Returns
    -------
    EffectSelection with the selected :class:`Terms`, the re-optimised resolution, its
    predicted ns per ray, and one :class:`Effect` per effect name.
    """
    if not tolerance >= 0:
        raise ValueError(f"tolerance must be >= 0, got {tolerance!r}")
    frac, p_hit = termination_fraction(stats) if termination else (1.0, 0.0)
    full = Terms(edge=True, area=True, mailbox=bool(mailbox), traversed_fraction=frac)
    res, h = optimal_uniform(stats, t_setup, t_step, t_int, overlap=overlap, terms=full)
    t_full = predict_uniform(stats, res, t_setup, t_step, t_int, overlap=overlap, terms=full)[0]

    def change(terms):
        t = predict_uniform(stats, res, t_setup, t_step, t_int, overlap=overlap, terms=terms)[0]
        return abs(t - t_full) / t_full

    n = stats.n_triangles
    effects = []
    ch = change(replace(full, edge=False))
    effects.append(Effect("edge", ch > tolerance, ch,
                          f"edge term: E1/h is {_pct(stats.e1 / h / n)} of N at h*; "
                          f"removing it changes time by {_pct(ch)}"))
    ch = change(replace(full, area=False))
    effects.append(Effect("area", ch > tolerance, ch,
                          f"area term: E2/h^2 is {_pct(stats.e2 / h ** 2 / n)} of N at h*; "
                          f"removing it changes time by {_pct(ch)}"))
    ch = change(replace(full, mailbox=not mailbox))
    if mailbox:
        effects.append(Effect("mailbox", ch > tolerance, ch,
                              f"mailboxing: counting repeated tests would change time by {_pct(ch)}"))
    else:
        effects.append(Effect("mailbox", False, 0.0,
                              f"mailboxing: kernel does not mailbox (it would change time by {_pct(ch)})"))
    if termination and rays_stop_on_entry(stats):
        effects.append(Effect("termination", False, 0.0,
                              f"termination (sampled, {stats.termination.rays} rays): {_pct(p_hit)} hit, every one "
                              "where it enters the box; the counts then fall with the cell size to the largest "
                              "grid (what bounds it, memory and the first cell's own triangles, is not in them), "
                              "so they are taken without termination"))
    elif termination:
        ch = change(replace(full, traversed_fraction=1.0))
        how = ("approximate" if stats.termination is None
               else f"sampled, {stats.termination.rays} rays")
        effects.append(Effect("termination", ch > tolerance, ch,
                              f"termination ({how}): ~{_pct(p_hit)} of rays hit, covering "
                              f"{_pct(frac)} of the no-hit distance (their first cell whole); ignoring it "
                              f"changes time by {_pct(ch)}"))
    else:
        effects.append(Effect("termination", False, 0.0, "termination: rays do not stop at hits"))
    disp = "" if dispersion is None else f"per-cell count dispersion {dispersion:.2f}x Poisson; "
    if levels == 1 or clustering_change is None:
        effects.append(Effect("clustering", False, 0.0,
                              f"clustering: {disp}uniform-grid counts are exact sums over cells, "
                              "so density changes them by 0.0%"))
    else:
        ch = float(clustering_change)
        effects.append(Effect("clustering", ch > tolerance, ch,
                              f"clustering: {disp}equal sub-scenes would change time by {_pct(ch)}"))
    if levels == 1:
        effects.append(Effect("subgrid", False, 0.0, "subgrid entry: single-level grid, no subgrids"))
    else:
        ch = float(subgrid_ns) / t_full
        effects.append(Effect("subgrid", ch > tolerance, ch,
                              f"subgrid entry: T_sub x subgrids is {_pct(ch)} of predicted time"))
    used = {e.name for e in effects if e.used}

    def selected(names):
        return Terms(edge="edge" in names, area="area" in names, mailbox=bool(mailbox) and "mailbox" in names,
                     traversed_fraction=frac if "termination" in names else 1.0)

    # Effects below tolerance one by one may not be together (the CAD tray: the edge and area
    # terms 1.4% each, a third of its tests jointly): put back the largest dropped term until
    # the selected model is within tolerance of the full one at the full optimum.
    droppable = {"edge", "area", "termination"} | ({"mailbox"} if mailbox else set())
    for e in sorted((e for e in effects if e.name in droppable and not e.used), key=lambda e: -e.change):
        if change(selected(used)) <= tolerance:
            break
        used.add(e.name)
        effects[effects.index(e)] = replace(e, used=True, reason=e.reason + (
            f"; kept: the terms below tolerance together change it by more than {_pct(tolerance)}"))
    terms = selected(used)
    res_sel, _ = optimal_uniform(stats, t_setup, t_step, t_int, overlap=overlap, terms=terms)
    t_sel = predict_uniform(stats, res_sel, t_setup, t_step, t_int, overlap=overlap, terms=terms)[0]
    return EffectSelection(terms=terms, resolution=res_sel, ns_per_ray=t_sel, effects=effects)
