"""What a batch of rays reads of a grid (calibrate/reach.py) and the share of it a cache keeps
(models.memory.weighted_miss_fraction).

Known answers: with every item read alike the weighted share is the cost model's
``1 - C/F``; against a simulated least-recently-used cache fed independent reads it is
within a few hundredths (Che's approximation); the walk enters, ray by ray, the cells the
instrumented kernel counts as steps.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np
import pytest

from calibrate._grid import Grid, Scene
from calibrate.rays import isotropic
from calibrate.reach import cell_bytes, cell_entries, read_miss_fraction
from models.memory import STEP_LINES, TEST_LINES, VISIT_LINES, miss_fraction, weighted_miss_fraction


# -- the weighted miss share ----------------------------------------------------------------

@pytest.mark.parametrize("i", range(4))
def test_items_read_alike_miss_one_minus_c_over_f(i):
    rng = np.random.default_rng(i)
    n = int(rng.integers(10, 5000))
    sizes = rng.uniform(8.0, 4096.0, n)
    cache = float(sizes.sum()) * rng.uniform(0.05, 0.95)
    rate = rng.uniform(1e-4, 1.0)
    got = weighted_miss_fraction(np.full(n, rate), sizes, cache)
    assert got == pytest.approx(float(miss_fraction(sizes.sum(), cache)), abs=1e-9)


def test_what_fits_or_is_never_read_does_not_miss(one_capacity):
    assert weighted_miss_fraction([0.5, 0.1], [100.0, 200.0], 300.0) == 0.0
    assert weighted_miss_fraction([0.0, 0.0], [1e6, 1e6], 10.0) == 0.0
    # an item never read does not take room: the two read ones fit
    assert weighted_miss_fraction([0.5, 0.5, 0.0], [100.0, 100.0, 1e9], 250.0) == 0.0


def test_a_hot_part_that_fits_keeps_the_misses_to_the_cold_rest(one_capacity):
    """Nine tenths of the reads go to a tenth of the bytes: with room for that tenth and a
    little more, the share missed is far below the whole grid's 1 - C/F, and it falls as the
    cache grows."""
    n = 1000
    sizes = np.full(n, 1000.0)
    rates = np.where(np.arange(n) < 100, 0.9 / 100, 0.1 / 900)
    shares = [weighted_miss_fraction(rates, sizes, c) for c in (1.2e5, 2e5, 4e5, 8e5)]
    assert shares[0] < 0.25 * float(miss_fraction(sizes.sum(), 1.2e5))
    assert all(a > b for a, b in zip(shares, shares[1:]))


def _lru_miss_share(rates, sizes, cache, reads, seed):
    """Bytes missed over bytes read by a least-recently-used cache of ``cache`` bytes, fed
    ``reads`` independent reads drawn by rate (the first tenth warms it up)."""
    rng = np.random.default_rng(seed)
    trace = rng.choice(len(rates), size=reads, p=np.asarray(rates) / np.sum(rates))
    held, used, missed, total = OrderedDict(), 0.0, 0.0, 0.0
    for k, item in enumerate(trace):
        counted = k >= reads // 10
        if item in held:
            held.move_to_end(item)
        else:
            if counted:
                missed += sizes[item]
            held[item] = True
            used += sizes[item]
            while used > cache:
                old, _ = held.popitem(last=False)
                used -= sizes[old]
        if counted:
            total += sizes[item]
    return missed / total


@pytest.mark.parametrize("i", range(3))
def test_the_share_matches_a_simulated_lru_cache(i, one_capacity):
    rng = np.random.default_rng(100 + i)
    n = 400
    sizes = rng.integers(1, 8, n).astype(float) * 64.0
    rates = rng.pareto(1.0 + i, n) + 1e-3  # from heavily skewed to mildly
    cache = float(sizes.sum()) * (0.2, 0.35, 0.5)[i]
    want = _lru_miss_share(rates, sizes, cache, 120_000, seed=i)
    assert weighted_miss_fraction(rates, sizes, cache) == pytest.approx(want, abs=0.03)


@pytest.mark.parametrize("rates, sizes, cache, message", [
    ([1.0], [1.0, 2.0], 1.0, "same length"),
    ([-1.0], [1.0], 1.0, "finite and >= 0"),
    ([np.nan], [1.0], 1.0, "finite and >= 0"),
    ([1.0], [-2.0], 1.0, "finite and >= 0"),
    ([1.0], [2.0], 0.0, "cache_bytes"),
    ([1.0], [2.0], np.inf, "cache_bytes"),
])
def test_bad_rates_sizes_and_caches_are_refused(rates, sizes, cache, message):
    with pytest.raises(ValueError, match=message):
        weighted_miss_fraction(rates, sizes, cache)


# -- the walk -------------------------------------------------------------------------------

@pytest.mark.parametrize("name, resolution", [("sphere", (9, 9, 9)), ("sphere", (23, 22, 23)),
                                              ("cylinder1996", (6, 6, 29)), ("cylinder1996", (19, 19, 12)),
                                              ("scattered-skinny", (14, 14, 14)), ("room", (31, 25, 10))])
def test_the_walk_enters_the_cells_the_kernel_counts_as_steps(name, resolution):
    scene = Scene.builtin(name)
    grid = Grid.uniform(scene, resolution)
    o, d = isotropic(scene.box_lo, scene.box_hi, 2048, seed=len(name) + resolution[2])
    entries, per_ray = cell_entries(grid, o, d)
    steps = grid.count(o, d)[0]
    mismatched = np.count_nonzero(per_ray != steps)
    assert mismatched <= 2, (mismatched, np.nonzero(per_ray != steps)[0][:5])  # a tie at a corner at most
    assert entries.sum() == per_ray.sum()
    assert entries.shape == (resolution[0] * resolution[1] * resolution[2],)


def test_rays_that_miss_the_box_enter_nothing_and_a_nested_grid_is_refused():
    scene = Scene.builtin("cylinder196")
    grid = Grid.uniform(scene, (4, 4, 16))
    o = np.array([[5.0, 5.0, -1.0], [0.0, 0.0, -1.0]])
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    entries, per_ray = cell_entries(grid, o, d)
    assert per_ray[0] == 0 and per_ray[1] >= 1 and entries.sum() == per_ray[1]
    with pytest.raises(ValueError, match="uniform"):
        cell_entries(Grid.nested(scene, 2), o, d)


def test_a_grid_that_fits_misses_nothing_and_the_bytes_are_the_kernels():
    scene = Scene.builtin("sphere")
    grid = Grid.uniform(scene, (12, 12, 12))
    o, d = isotropic(scene.box_lo, scene.box_hi, 1024, seed=7)
    got = read_miss_fraction(grid, o, d, 1 << 30)
    assert got["weighted"] == 0.0 and got["whole"] == 0.0
    # the kernel's bytes less its fixed header, one node and the records of the empty cells, which a
    # step does not read (their occupancy bits say they are empty)
    empty = int(np.count_nonzero(np.asarray(grid.top_counts()) == 0))
    assert 0 < empty < 12 ** 3
    assert cell_bytes(grid).sum() + 8 * empty == pytest.approx(got["memory_bytes"], rel=0.01)
    assert 0 < got["read_bytes"] <= cell_bytes(grid).sum()


# -- the memory term on what rays read (models.memory.read_bytes) -----------------------------

from calibrate import predict as P  # noqa: E402
from models.memory import read_bytes  # noqa: E402
from models.stats import TriangleSample, triangle_sample  # noqa: E402

# a host's isotropic constants of the order measured (docs/calibration.md), ns; a 16 MiB cache
CONSTANTS = dict(t_setup_ns=55.0, t_step_ns=6.5, t_int_ns=1.05, t_sub_ns=38.0, t_visit_ns=5.5, t_mem_ns=12.6,
                 cache_bytes=16 << 20)


def test_copies_read_alike_are_charged_as_the_whole_grid():
    """Triangles of one orientation in cells of one shape are read at one rate: with no cell records
    the weighted share is 1 - C/F and the bytes charged are the grid's."""
    rng = np.random.default_rng(0)
    ext = np.column_stack([rng.uniform(0.1, 1.0, 200), rng.uniform(0.1, 1.0, 200), np.zeros(200)])
    proj = np.column_stack([np.zeros(200), np.zeros(200), 0.5 * ext[:, 0] * ext[:, 1]])  # all facing z
    sample = TriangleSample(extents=ext, proj_areas=proj, areas=proj[:, 2].copy(), weight=3.0)
    extent, res = np.array([4.0, 4.0, 4.0]), (16, 16, 16)
    c = extent / np.array(res)
    copies = 3.0 * (1.0 + ext @ (1.0 / c) + proj @ (1.0 / np.array([c[1] * c[2], c[2] * c[0], c[0] * c[1]])))
    grid = 76.0 * copies.sum()
    assert read_bytes(sample, extent, res, 10.0, 30.0, grid, grid / 3, cell_bytes=0.0) == pytest.approx(grid, rel=1e-9)
    # no sample, no cache, or a grid that fits: the grid's bytes
    assert read_bytes(None, extent, res, 10.0, 30.0, grid, grid / 3) == grid
    assert read_bytes(sample, extent, res, 10.0, 30.0, grid, None) == grid
    assert read_bytes(sample, extent, res, 10.0, 30.0, grid, 2 * grid) == grid


def test_a_triangle_sample_is_strided_and_checked():
    scene = Scene.builtin("cylinder1996")
    s = triangle_sample(scene.vertices, scene.faces, size=500)
    assert s.extents.shape == (499, 3) and s.weight == pytest.approx(1996 / 499)
    assert np.all(s.proj_areas.sum(axis=1) >= s.areas * (1 - 1e-12))  # A |n|_1 >= A
    with pytest.raises(ValueError, match="weight"):
        TriangleSample(extents=s.extents, proj_areas=s.proj_areas, areas=s.areas, weight=0.5)
    with pytest.raises(ValueError, match="areas"):
        TriangleSample(extents=s.extents, proj_areas=s.proj_areas, areas=s.areas[:-1], weight=2.0)
    with pytest.raises(ValueError, match="finite"):
        TriangleSample(extents=-s.extents, proj_areas=s.proj_areas, areas=s.areas, weight=2.0)


def test_the_long_cylinders_end_caps_are_read_little_in_the_model_as_by_its_rays():
    """`cylinder19996`: at 12 cells along the axis its end caps hold most of the references, in
    cells rays seldom enter; at 48 the wall holds most.  The model's charged bytes and the share
    the batch's own reads miss (reach.read_miss_fraction) both say far less misses at 12 than the
    whole grid's 1 - C/F, and less at 12 than at 48 (0.16 and 0.06 at 12, 0.70 and 0.59 at 48,
    against 0.67 and 0.79 for the whole grid)."""
    scene = Scene.builtin("cylinder19996")
    stats = P.scene_statistics(scene)
    k = P.resolve_constants(constants=CONSTANTS)
    terms = P.analytic_uniform_plan(stats, k, False)[0]["terms"]
    o, d = isotropic(scene.box_lo, scene.box_hi, 65536, seed=12)  # rates of the cells entered seldom
    shares = {}
    for res in ((65, 65, 12), (65, 65, 48)):
        steps, tests, _, mem, _, charged = P._uniform_counts(stats, res, k, terms)
        model = float(miss_fraction(charged, k.cache_bytes))
        measured = read_miss_fraction(Grid.uniform(scene, res), o, d, k.cache_bytes)
        assert model < float(miss_fraction(mem, k.cache_bytes)) - 0.05
        assert measured["weighted"] < measured["whole"] - 0.1
        assert abs(model - measured["weighted"]) < 0.2, (res, model, measured)
        shares[res] = (model, measured["weighted"])
    assert shares[(65, 65, 12)][0] < shares[(65, 65, 48)][0] and shares[(65, 65, 12)][1] < shares[(65, 65, 48)][1]


def test_the_long_cylinder_is_planned_with_cells_long_along_its_axis():
    """Priced on what rays read, the plan's cells are long along the axis (few cells along z), and
    with the kernel's counts and the batch's reads it is cheaper than the near-cubic plan the
    whole grid's memory term made (106x106x170; measured 3.1 times slower, docs/calibration.md)."""
    scene = Scene.builtin("cylinder19996")
    k = P.resolve_constants(constants=CONSTANTS)
    out = P.predict(scene, constants=CONSTANTS, levels="1")
    res = tuple(out["levels"][0]["resolution"])
    cells = scene.box_hi - scene.box_lo
    cell = cells / np.array(res)
    assert cell[2] >= 4 * max(cell[0], cell[1]), res
    assert any(e["name"] == "cell-shape" and e["used"] for e in out["effects"])
    o, d = isotropic(scene.box_lo, scene.box_hi, 8192, seed=13)

    def kernel_price(r):
        grid = Grid.uniform(scene, r)
        steps, tests, _, visits = (float(x.mean()) for x in grid.count(o, d, visits=True))
        share = read_miss_fraction(grid, o, d, k.cache_bytes)["weighted"]
        lines = STEP_LINES * steps + VISIT_LINES * visits + TEST_LINES * tests
        return k.cost(steps, tests, 0.0, 0.0, visits) + k.t_mem * share * lines

    assert kernel_price(res) < 0.7 * kernel_price((106, 106, 170))
