"""Box's epsilon of the targeted tests (:func:`_sphericity_epsilon`): the F(p, (R-1) p)
reference of a sum of squares over p directions holds when the noise is spherical in them;
when one channel is noisier than the others along a term's directions the sums spread like
fewer dof and the plain test rejects too often. Checked by Monte Carlo against the known
covariance (seeded)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import special

from calib_core.discovery.noise import sphericity_epsilon as _sphericity_epsilon

R = 5  # the production protocol's repetitions


def _rates(variances: list[list[float]], n: int, seed: int) -> tuple[float, float, float]:
    """(plain, corrected) rejection rates at 1 % of the pooled F test of a zero mean, and the
    mean epsilon, over ``n`` draws of R repetitions with the given per-channel variances."""
    rng = np.random.default_rng(seed)
    sd = [np.sqrt(np.asarray(v, float)) for v in variances]
    p = sum(len(v) for v in variances)
    plain = corrected = 0
    eps_sum = 0.0
    for _ in range(n):
        Z = [rng.normal(size=(R, len(s))) * s for s in sd]
        num = sum(R * np.sum(z.mean(axis=0) ** 2) for z in Z)
        devs = [z - z.mean(axis=0) for z in Z]
        F = (num / p) / (sum(np.sum(d**2) for d in devs) / ((R - 1) * p))
        eps = _sphericity_epsilon(devs)
        eps_sum += eps
        plain += special.fdtrc(p, (R - 1) * p, F) < 0.01
        corrected += special.fdtrc(eps * p, eps * (R - 1) * p, F) < 0.01
    return plain / n, corrected / n, eps_sum / n


def test_epsilon_is_one_on_a_single_direction_and_bounded():
    rng = np.random.default_rng(1)
    assert _sphericity_epsilon([]) == 1.0  # no direction the affine model leaves
    assert _sphericity_epsilon([rng.normal(size=(R, 1))]) == 1.0
    for _ in range(200):
        blocks = [rng.normal(size=(R, k)) * rng.uniform(0.1, 10.0, size=k) for k in (1, 2, 3)]
        blocks = [b - b.mean(axis=0) for b in blocks]
        assert 1.0 / 6.0 <= _sphericity_epsilon(blocks) <= 1.0


@pytest.mark.slow
def test_a_noisier_channel_no_longer_inflates_the_false_alarms():
    """Six channels, one 10x the others' variance (true epsilon 0.36): the plain F rejects
    about 5.5 % at 1 %; corrected, about 3.3 % (four dof per direction see the heterogeneity
    only in part: the estimate averages 0.55). Spherical noise: both stay at or under 1 %
    (binomial sd 0.1 % over 8,000 draws)."""
    plain, corrected, eps = _rates([[1.0]] * 5 + [[10.0]], 8000, seed=7)
    assert plain > 0.04, plain  # the failure being corrected is there
    assert corrected < 0.7 * plain, (plain, corrected)
    assert eps < 0.7, eps  # the estimate sees the heterogeneity (spherical: about 0.94)
    plain, corrected, eps = _rates([[1.0]] * 6, 8000, seed=8)
    assert plain <= 0.0125 and corrected <= 0.0125, (plain, corrected)
    assert eps > 0.85, eps
