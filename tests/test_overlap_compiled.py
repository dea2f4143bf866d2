"""The kernels' triangle/box test, vectorised for the nested-grid planner, against the
numpy reference of models.nested (both are the separating-axis test of Akenine-Moller)."""

from __future__ import annotations

import numpy as np
import pytest

from calibrate._grid import triangle_box_overlap
from models.nested import triangle_box_overlap as reference


def _cases(seed: int, n: int = 20_000):
    rng = np.random.default_rng(seed)
    centre = rng.uniform(-1, 1, (n, 1, 3))
    tri = centre + rng.normal(scale=rng.choice([0.01, 0.3, 2.0], (n, 1, 1)), size=(n, 3, 3))
    skinny = rng.random(n) < 0.2  # slivers: the third corner near the first edge
    tri[skinny, 2] = tri[skinny, 0] + 0.5 * (tri[skinny, 1] - tri[skinny, 0]) + 1e-6 * rng.normal(size=(skinny.sum(), 3))
    size = rng.uniform(0.01, 1, (n, 3))
    lo = tri.mean(axis=1) + rng.normal(scale=0.5, size=(n, 3)) - 0.5 * size  # boxes near the triangles
    hi = lo + size
    return tri, lo, hi


@pytest.mark.parametrize("seed", range(4))
def test_compiled_overlap_equals_the_reference(seed):
    tri, lo, hi = _cases(seed)
    got, want = triangle_box_overlap(tri, lo, hi), reference(tri, lo, hi)
    assert got.dtype == bool and got.shape == want.shape
    # Both sides hit and miss in good numbers, so agreement is not trivial.
    assert 0.1 < want.mean() < 0.9
    assert np.array_equal(got, want), f"{int((got != want).sum())} of {got.size} pairs disagree"


def test_compiled_overlap_touching_boxes_count_as_overlapping():
    tri = np.array([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]])
    # a box whose face contains the triangle's corner (closed sets touch), and one just beyond it
    assert triangle_box_overlap(tri, np.array([[1.0, -1, -1]]), np.array([[2.0, 1, 1]]))[0]
    assert not triangle_box_overlap(tri, np.array([[1.0 + 1e-9, -1, -1]]), np.array([[2.0, 1, 1]]))[0]


def test_compiled_overlap_rejects_mismatched_shapes():
    tri, lo, hi = _cases(0, 4)
    with pytest.raises(ValueError, match="shape"):
        triangle_box_overlap(tri, lo[:3], hi)
