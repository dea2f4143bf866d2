"""The talk's closed forms, their brute-force minima, cells -> resolution, and the baselines."""

from __future__ import annotations

import numpy as np
import pytest

from models.baselines import (all_baselines, cleary_grid, kalojanov_leaf_resolution, kalojanov_two_level,
                              manta_level_cells, manta_recursive_grid, pbrt_grid)
from models.closed_forms import (MAX_CELLS_PER_AXIS, MAX_TOTAL_CELLS, cells_to_resolution, empirical_cells,
                                 l_level_cells, lines_cells, points_cells, two_level_lines, two_level_points)


def _argmin_log(f, lo, hi, n=200001):
    """Brute-force minimiser of f on a log grid (a known answer independent of calculus)."""
    x = np.exp(np.linspace(np.log(lo), np.log(hi), n))
    return x[np.argmin(f(x))]


@pytest.mark.parametrize("i", range(4))
def test_talk_formulas_exactly(i):
    rng = np.random.default_rng(2000 + i)
    n, r, k = rng.uniform(10, 1e6), rng.uniform(0.5, 20), rng.uniform(1, 10)
    assert points_cells(n, r) == 2 * n * r
    assert lines_cells(n, r) == (n * r) ** 1.5
    m1, m2 = two_level_points(n, r, k)
    assert m1 == pytest.approx((2 * k ** 2 * n * r) ** 0.6, rel=1e-14)
    assert m2 == pytest.approx((2 * n * r / k ** 3) ** 0.6, rel=1e-14)
    # the L-level recursion reproduces the 1- and 2-level laws
    assert l_level_cells(n, r, 1)[0] == pytest.approx(2 * n * r, rel=1e-14)
    np.testing.assert_allclose(l_level_cells(n, r, 2, k), [m1, m2], rtol=1e-12)
    np.testing.assert_allclose(l_level_cells(n, r, 2, k, kind="lines"), two_level_lines(n, r, k), rtol=1e-12)
    assert l_level_cells(n, r, 1, kind="lines")[0] == pytest.approx((n * r) ** 1.5, rel=1e-14)


@pytest.mark.parametrize("i", range(3))
def test_closed_forms_are_brute_force_minima(i):
    """Minimise the talk's cost expressions numerically; the closed forms must agree."""
    rng = np.random.default_rng(2100 + i)
    n, r, k = rng.uniform(1e3, 1e6), rng.uniform(1, 10), rng.uniform(2, 8)
    m = _argmin_log(lambda m: m + n / m ** 2 * r, 1, 1e6)
    assert m ** 3 == pytest.approx(points_cells(n, r), rel=1e-3)
    m = _argmin_log(lambda m: m + n / m * r, 1, 1e6)
    assert m ** 3 == pytest.approx(lines_cells(n, r), rel=1e-3)

    # 2-level points: T = m1 + k * C1(N / (k m1^2)), C1(N2) = min_m2 m2 + N2 r / m2^2.
    def c1_points(n2):
        m2 = (2 * n2 * r) ** (1 / 3)
        return m2 + n2 * r / m2 ** 2
    m1 = _argmin_log(lambda m: m + k * c1_points(n / (k * m * m)), 1, 1e5)
    assert m1 ** 3 == pytest.approx(two_level_points(n, r, k)[0], rel=1e-3)

    # 2-level lines: T = m1 + k * C1(N / (k m1)), C1(N2) = min_m2 m2 + N2 r / m2.
    def c1_lines(n2):
        m2 = np.sqrt(n2 * r)
        return m2 + n2 * r / m2
    m1 = _argmin_log(lambda m: m + k * c1_lines(n / (k * m)), 1, 1e5)
    assert m1 ** 3 == pytest.approx(two_level_lines(n, r, k)[0], rel=1e-3)

    # 3-level points: the top of the recursion is the brute-force minimum over m1 of
    # m1 + k * C2(N / (k m1^2)), with C2 the brute-force 2-level cost.
    def c2(n2):
        m = (2 * k * k * n2 * r) ** 0.2
        return m + k * c1_points(n2 / (k * m * m))
    m1 = _argmin_log(lambda m: m + k * c2(n / (k * m * m)), 1, 1e5)
    assert m1 ** 3 == pytest.approx(l_level_cells(n, r, 3, k)[0], rel=1e-3)


def test_l_level_exponent():
    """Top cells grow as N^(3/(2L+1)) (points) and N^(3/(L+1)) (lines)."""
    for levels in (1, 2, 3, 4):
        a = l_level_cells(1e4, 3.0, levels, 5.0)[0]
        b = l_level_cells(1e6, 3.0, levels, 5.0)[0]
        assert np.log(b / a) / np.log(100) == pytest.approx(3 / (2 * levels + 1), rel=1e-12)
        a = l_level_cells(1e4, 3.0, levels, 5.0, kind="lines")[0]
        b = l_level_cells(1e6, 3.0, levels, 5.0, kind="lines")[0]
        assert np.log(b / a) / np.log(100) == pytest.approx(3 / (levels + 1), rel=1e-12)


def test_empirical_laws():
    assert empirical_cells(1e6, "compact", 2.0) == pytest.approx(2.0 * 1e6 ** (7 / 9))
    assert empirical_cells(1e3, "long-skinny", 0.5) == pytest.approx(0.5 * 1e3 ** (4 / 3))
    with pytest.raises(ValueError):
        empirical_cells(10, "mixed")


def test_cells_to_resolution_talk_rule():
    # exact cube roots: M = 8000 over a 1 x 2 x 4 box -> h = (8/8000)^(1/3) = 0.1
    assert cells_to_resolution(8000, [1, 2, 4]) == (10, 20, 40)
    assert cells_to_resolution(1000, [3, 3, 3]) == (10, 10, 10)


@pytest.mark.parametrize("extent", [[1, 1, 1], [356, 3.2, 356], [1, 1e-3, 1e-3], [1e20, 1e-20, 1], [5, 5, 61]])
@pytest.mark.parametrize("cells", [1e-30, 1.0, 2.0 * 1 * 5, 2.0 * 1e7 * 5, (1e7 * 5) ** 1.5, 1e300, np.inf])
def test_cells_to_resolution_clamped_and_finite(extent, cells):
    n = cells_to_resolution(cells, extent)
    assert all(isinstance(x, int) for x in n)
    assert all(1 <= x <= MAX_CELLS_PER_AXIS for x in n)
    assert n[0] * n[1] * n[2] <= MAX_TOTAL_CELLS
    if cells >= MAX_TOTAL_CELLS:  # the clamp keeps the grid close to the cap, not tiny
        assert n[0] * n[1] * n[2] >= MAX_TOTAL_CELLS / 8 or max(n) == MAX_CELLS_PER_AXIS


def test_cells_to_resolution_bad_input():
    for bad in ((0, [1, 1, 1]), (-1, [1, 1, 1]), (np.nan, [1, 1, 1]), (10, [1, 0, 1]), (10, [1, np.inf, 1]),
                (10, [1, 1])):
        with pytest.raises(ValueError):
            cells_to_resolution(*bad)


def test_pbrt_baseline():
    # N = 8: 3 * 2 = 6 voxels along the longest axis, others proportional, rounded half up.
    assert pbrt_grid(8, [2, 1, 0.5]) == (6, 3, 2)
    assert pbrt_grid(1e9, [1, 1, 1]) == (64, 64, 64)  # the clamp
    assert pbrt_grid(1, [1, 1e-6, 1]) == (3, 1, 3)


def test_manta_and_cleary_baselines():
    assert manta_level_cells(1000, 1, 0) == pytest.approx(8000)  # 8N cells for L = 1
    assert manta_level_cells(1000, 2, 0) == pytest.approx(8000 ** 0.6)  # (8N)^(3/5): talk's L = 2 exponent
    assert manta_level_cells(50, 2, 1) == pytest.approx(400)  # a depth-1 subgrid: 8 n cells
    assert manta_recursive_grid(1000, [1, 1, 1]) == (20, 20, 20)
    assert cleary_grid(200, [1, 1, 1]) == (10, 10, 10)  # 5 N = 1000 cells
    with pytest.raises(ValueError):
        manta_level_cells(10, 2, 2)


def test_kalojanov_baseline():
    top, leaf = kalojanov_two_level(16000, [1, 1, 1])
    assert top == (10, 10, 10)  # N / 16 = 1000 cells
    assert leaf == (3, 3, 3)  # 16 refs per cell * 1.2 = 19.2 cells -> 2.68 per axis -> 3
    assert kalojanov_leaf_resolution(0, [1, 1, 1]) == (1, 1, 1)
    _, leaf = kalojanov_two_level(16000, [1, 1, 1], cell_refs=[0, 100, 100, 5])
    assert leaf == (5, 5, 5)  # median of non-empty 100 -> 120 cells


def test_all_baselines_on_flat_and_huge_scenes():
    from models.stats import scene_stats

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float64)
    s = scene_stats(v, np.array([[0, 1, 2]]))  # N = 1, flat box
    for name, levels in all_baselines(s).items():
        for res in levels:
            assert all(1 <= x for x in res), name
    for fn in (manta_recursive_grid, cleary_grid):
        n = fn(1e7, [1, 1e-3, 1])
        assert n[0] * n[1] * n[2] <= MAX_TOTAL_CELLS
