"""Effect selection: the tolerance rule, known scenes, and the termination model against Monte Carlo."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_models_general import chord_end, mesh_of, random_triangles, sample_lines

from models.effects import (EFFECT_TOLERANCE, clustering_index, rays_stop_on_entry, select_effects,
                            termination_fraction)
from models.stats import TerminationSample, scene_stats, stats_from_geometry, triangle_geometry

T = dict(t_setup=20.0, t_step=2.0, t_int=8.0)


def _scene(i, scale, skinny=False, n=2000):
    rng = np.random.default_rng(6000 + i)
    tri = random_triangles(rng, n, (1, 1, 1), scale, skinny=skinny, margin=0.0)
    return stats_from_geometry(triangle_geometry(*mesh_of(tri)), [0, 0, 0], [1, 1, 1])


def _by_name(sel):
    return {e.name: e for e in sel.effects}


def test_edge_term_dropped_for_points_kept_for_lines():
    tiny = _by_name(select_effects(_scene(0, 1e-5), **T, termination=False))
    assert not tiny["edge"].used and tiny["edge"].change < EFFECT_TOLERANCE
    assert not tiny["area"].used
    skinny = _by_name(select_effects(_scene(1, 0.3, skinny=True), **T, termination=False))
    assert skinny["edge"].used and skinny["edge"].change > EFFECT_TOLERANCE
    assert "of N at h*" in skinny["edge"].reason


def test_tolerance_boundary_flips_the_decision():
    """An effect is kept iff its measured change exceeds the tolerance, unless the effects below
    it together change the time by more: then the largest of them is put back, said in its reason."""
    s = _scene(2, 0.05)
    e = _by_name(select_effects(s, **T, termination=False))
    edge, area = e["edge"].change, e["area"].change
    assert 0 < edge < area / 1.1 < area
    for name in ("edge", "area"):
        ch = e[name].change
        assert _by_name(select_effects(s, **T, termination=False, tolerance=0.9 * ch))[name].used
    # between the two: edge dropped alone, area kept on its own merit
    mid = _by_name(select_effects(s, **T, termination=False, tolerance=1.1 * edge))
    assert not mid["edge"].used and mid["area"].used and "kept" not in mid["area"].reason
    # above both: each is below, together they are not; area (the larger) is put back
    top = _by_name(select_effects(s, **T, termination=False, tolerance=1.1 * area))
    assert not top["edge"].used and top["area"].used and "together" in top["area"].reason


@pytest.mark.parametrize("i", range(4))
def test_selected_terms_predict_within_tolerance_of_the_full_model(i):
    """The joint rule: at the full model's optimum, the selected terms' predicted time is within
    the tolerance of the full model's (each effect is judged alone first)."""
    from models.general import Terms, optimal_uniform, predict_uniform

    s = _scene(20 + i, [0.02, 0.05, 0.1, 0.2][i], skinny=bool(i % 2))
    e = _by_name(select_effects(s, **T, termination=True))
    # just above the larger of edge and area: each is dropped alone, not both together
    for tol in (0.02, 1.05 * max(e["edge"].change, e["area"].change)):
        sel = select_effects(s, **T, termination=True, tolerance=tol)
        frac, _ = termination_fraction(s)
        full = Terms(traversed_fraction=frac)
        res, _ = optimal_uniform(s, T["t_setup"], T["t_step"], T["t_int"], terms=full)
        t_full = predict_uniform(s, res, T["t_setup"], T["t_step"], T["t_int"], terms=full)[0]
        t_sel = predict_uniform(s, res, T["t_setup"], T["t_step"], T["t_int"], terms=sel.terms)[0]
        assert abs(t_sel - t_full) / t_full <= tol + 1e-12


def test_dropping_effects_changes_the_prediction_by_less_than_their_sum():
    s = _scene(3, 0.01)
    sel = select_effects(s, **T, termination=False)
    full = select_effects(s, **T, termination=False, tolerance=0.0)
    dropped = sum(e.change for e in sel.effects if not e.used)
    assert abs(sel.ns_per_ray - full.ns_per_ray) / full.ns_per_ray <= dropped + 1e-9


def test_mailbox_effect_only_for_mailboxing_kernels():
    s = _scene(4, 0.2)
    off = _by_name(select_effects(s, **T, termination=False, mailbox=False))["mailbox"]
    on = _by_name(select_effects(s, **T, termination=False, mailbox=True))["mailbox"]
    assert not off.used and "does not mailbox" in off.reason
    assert on.used and on.change > EFFECT_TOLERANCE


def test_single_level_reports_clustering_and_subgrid_as_unused():
    e = _by_name(select_effects(_scene(5, 0.01), **T, dispersion=4.2))
    assert not e["clustering"].used and "4.20x Poisson" in e["clustering"].reason
    assert not e["subgrid"].used
    e = _by_name(select_effects(_scene(5, 0.01), **T, levels=2, subgrid_ns=50.0, clustering_change=0.001))
    assert e["subgrid"].used and not e["clustering"].used


def test_clustering_index_known_answers():
    assert clustering_index(np.full(100, 7)) == 0.0
    rng = np.random.default_rng(6100)
    assert clustering_index(rng.poisson(5.0, 200_000)) == pytest.approx(1.0, rel=0.02)
    with pytest.raises(ValueError):
        clustering_index([])


def test_termination_hit_probability_is_exact_for_a_centred_sphere():
    """Crofton: P(hit | hit box) = A / S for a convex closed surface. Distance model: approximate."""
    trimesh = pytest.importorskip("trimesh")
    m = trimesh.creation.icosphere(subdivisions=5, radius=0.5)
    v = np.asarray(m.vertices) * 0.6 + 1.0  # sphere of radius 0.3 centred in a [0, 2]^3 box
    f = np.asarray(m.faces, dtype=np.int64)
    closed = scene_stats(v, f)
    s = stats_from_geometry(triangle_geometry(v, f), [0, 0, 0], [2, 2, 2], watertight=closed.watertight,
                            enclosed=closed.enclosed_volume)
    assert s.watertight and np.allclose(s.extent, 2.0)
    frac, p = termination_fraction(s)
    rng = np.random.default_rng(6200)
    o, w = sample_lines(rng, s.extent, 400_000)
    t_out = chord_end(o, w, s.extent)
    oc = o - 1.0  # sphere centre at (1, 1, 1), radius 0.3 (the mesh is inscribed: area 0.2% lower)
    b = np.einsum("ij,ij->i", oc, w)
    disc = b * b - (np.einsum("ij,ij->i", oc, oc) - 0.09)
    hit = disc > 0
    t_hit = np.where(hit, -b - np.sqrt(np.maximum(disc, 0)), t_out)
    assert hit.mean() == pytest.approx(p, rel=0.02)
    # traversed fraction: documented as approximate (mean chords, not conditional ones)
    assert t_hit.mean() / t_out.mean() == pytest.approx(frac, rel=0.1)


def test_termination_fraction_bounds():
    s = _scene(6, 0.3)
    frac, p = termination_fraction(s)
    assert 0 < frac <= 1 and 0 <= p <= 1
    open_plane = replace(s, watertight=False, area=10 * s.surface)
    assert termination_fraction(open_plane) == (pytest.approx(0.5), 1.0)
    closed_box = replace(s, watertight=True, area=s.surface, enclosed_volume=s.volume)
    assert termination_fraction(closed_box)[0] == pytest.approx(1e-6)  # floor: rays stop at entry


def test_a_sampled_termination_replaces_the_approximation():
    s = _scene(7, 0.3)
    sampled = replace(s, termination=TerminationSample(fraction=0.0371, p_hit=0.82, rays=4096))
    assert termination_fraction(sampled) == (0.0371, 0.82)
    assert termination_fraction(s) != termination_fraction(sampled)
    sel = _by_name(select_effects(sampled, **T))
    assert sel["termination"].used and "sampled, 4096 rays" in sel["termination"].reason
    assert "3.7% of the no-hit distance" in sel["termination"].reason
    assert "approximate" in _by_name(select_effects(s, **T))["termination"].reason
    # a smaller traversed fraction makes the first cell's triangles weigh more: a finer optimum
    farther = replace(s, termination=TerminationSample(fraction=0.5, p_hit=0.82, rays=4096))
    assert np.prod(select_effects(sampled, **T).resolution) > np.prod(select_effects(farther, **T).resolution)


def test_rays_that_stop_where_they_enter_are_counted_without_termination():
    """Below one ray's chord in all (the room's walls are the box's faces) the count model would
    refine to the largest grid; the counts are then those of rays that never stop, said so."""
    s = _scene(8, 0.3)
    one_ray = 1.0 / 4096
    on_entry = replace(s, termination=TerminationSample(fraction=0.99 * one_ray, p_hit=1.0, rays=4096))
    past = replace(s, termination=TerminationSample(fraction=1.01 * one_ray, p_hit=1.0, rays=4096))
    assert rays_stop_on_entry(on_entry) and not rays_stop_on_entry(past) and not rays_stop_on_entry(s)
    assert termination_fraction(on_entry) == (1.0, 1.0)
    assert termination_fraction(past)[0] == pytest.approx(1.01 * one_ray)
    sel = select_effects(on_entry, **T)
    e = _by_name(sel)["termination"]
    assert not e.used and "where it enters the box" in e.reason and sel.terms.traversed_fraction == 1.0
    assert sel.resolution == select_effects(s, **T, termination=False).resolution
    # without the rule: the optimum runs far finer on a fraction the sample cannot resolve
    assert np.prod(select_effects(past, **T).resolution) > 8 * np.prod(sel.resolution)


@pytest.mark.parametrize("bad", [dict(fraction=-0.1, p_hit=0.5, rays=10), dict(fraction=0.2, p_hit=1.5, rays=10),
                                 dict(fraction=float("nan"), p_hit=0.5, rays=10),
                                 dict(fraction=0.2, p_hit=0.5, rays=0), dict(fraction=0.2, p_hit=0.5, rays=2.5),
                                 dict(fraction=0.2, p_hit=0.5, rays=True)])
def test_a_termination_sample_rejects_bad_values(bad):
    with pytest.raises(ValueError):
        TerminationSample(**bad)
