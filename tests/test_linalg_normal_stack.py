"""calib_core.linalg.solve_normal_stack: the pseudo-inverse's solution of stacked normal
equations, also where a design has a zero column or dependent columns."""

import numpy as np

from calib_core.linalg import solve_normal_stack


def _normal(X, w):
    Xw = X * w[..., None]
    return Xw.transpose(0, 2, 1) @ X


def test_well_posed_problems_match_the_pseudo_inverse():
    rng = np.random.default_rng(7)
    X = rng.normal(size=(20, 60, 6)) * np.array([1.0, 80.0, 80.0, 700.0, 1.0, 1.0])
    w = rng.uniform(0.0, 1.0, size=(20, 60))
    y = rng.normal(size=(20, 60, 1))
    A, b = _normal(X, w), (X * w[..., None]).transpose(0, 2, 1) @ y
    x = solve_normal_stack(A, b)
    ref = np.linalg.pinv(A) @ b
    np.testing.assert_allclose(x, ref, rtol=1e-10, atol=0)


def test_zero_and_dependent_columns_give_the_minimum_norm_fit():
    rng = np.random.default_rng(8)
    X = rng.normal(size=(3, 40, 6))
    X[0, :, 4:] = 0.0  # no times: the time columns are zero
    X[1, :, 2] = 3.0 * X[1, :, 1]  # two columns in proportion: singular
    y = rng.normal(size=(3, 40, 1))
    w = np.ones((3, 40))
    A, b = _normal(X, w), X.transpose(0, 2, 1) @ y
    x = solve_normal_stack(A, b)
    ref = np.linalg.pinv(A) @ b
    assert np.all(x[0, 4:] == 0.0)
    np.testing.assert_allclose(x[:2], ref[:2], rtol=1e-8, atol=1e-12)
    # the fitted values (what the check uses) are those of an ordinary least squares
    fit = X @ x
    for r in range(3):
        coef = np.linalg.lstsq(X[r], y[r], rcond=None)[0]
        np.testing.assert_allclose(fit[r], X[r] @ coef, rtol=1e-9, atol=1e-12)


def test_masked_problems_take_the_pseudo_inverse_bit_for_bit():
    rng = np.random.default_rng(9)
    X = rng.normal(size=(5, 30, 6))
    y = rng.normal(size=(5, 30, 1))
    A, b = _normal(X, np.ones((5, 30))), X.transpose(0, 2, 1) @ y
    mask = np.array([True, False, True, False, False])
    x = solve_normal_stack(A, b, mask)
    ref = np.linalg.pinv(A) @ b
    assert np.array_equal(x[mask], ref[mask])
    assert np.array_equal(solve_normal_stack(A, b, True), ref)


def test_consistency_fit_of_mostly_exact_zeros_keeps_the_pseudo_inverse_rounding():
    """The step check's problem whose values are mostly exactly 0 (the median repetition's
    deviations) ends on an exact fit, where rounding sets the weights: it is solved by the
    pseudo-inverse throughout, so its residuals are those of that solve bit for bit."""
    from calib_core.guards import _irls_residuals, _robust_affine_residuals

    rng = np.random.default_rng(10)
    n = 118
    X = np.concatenate(
        [np.ones((2, n, 1)), rng.normal(scale=70.0, size=(2, n, 3)), rng.normal(size=(2, n, 2))], axis=2
    )
    d = rng.normal(scale=1e-3, size=(2, n))
    d[0, rng.permutation(n)[:70]] = 0.0  # more than half exactly 0
    d[0, 5] = 6.7  # one damaged step
    out = _robust_affine_residuals(d, X)
    assert np.array_equal(out[0], _irls_residuals(d[:1], X[:1], True)[0][0])
    np.testing.assert_allclose(out[1], _irls_residuals(d[1:], X[1:], True)[0][0], rtol=1e-8, atol=1e-15)
