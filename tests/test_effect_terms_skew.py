"""skew() is filled in place now: it must still be the cross-product matrix."""

from __future__ import annotations

import numpy as np

from calib_core.effects import skew


def test_skew_is_the_cross_product():
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    S = skew(a)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", S, b), np.cross(a, b), rtol=0, atol=1e-14)
    np.testing.assert_array_equal(S, -np.swapaxes(S, 1, 2))
    assert skew(np.array([1.0, 2.0, 3.0])).shape == (1, 3, 3)
    assert skew(np.array([[1, 2, 3]])).dtype == np.float64  # integer rows: float matrices
