"""The pure-error dof a step-mean variance costs (:func:`_variance_dof_cost`): a variance
estimated from the repetitions' scatter and used to weight the rows that are then tested
against that same scatter makes the lack-of-fit F optimistic by E[1 / q] = d / (d - 2) (2 dof,
not the 1 of a fitted parameter); a variance that is mostly the known within-step white part
costs nothing. Checked by Monte Carlo on a toy of the weighting alone (seeded): test groups
with their own dof, weight 1 / max(s^2, w^2), the weighted pure error and lack of fit of each."""

from __future__ import annotations

import numpy as np
import pytest

from calib_core.discovery.noise import variance_dof_cost as _variance_dof_cost

# the default protocol's test groups on 5 repetitions: pure-error dof and lack-of-fit dof
PURE_DOF = np.array([92, 128, 240])
LOF_DOF = np.array([20, 30, 64])


def _mean_f_ratio(white_share: float, counted: np.ndarray, n: int = 40_000, seed: int = 3) -> float:
    """E[lack of fit / its dof] / E[pure error / its dof net of ``counted``] over ``n`` draws
    of the three groups, each with step variance 1 of which ``white_share`` is the known
    white part: 1 when the count is right."""
    rng = np.random.default_rng(seed)
    s2 = rng.chisquare(PURE_DOF, size=(n, 3)) / PURE_DOF  # each group's estimated variance
    weight = 1.0 / np.maximum(s2, white_share)
    lof = rng.chisquare(LOF_DOF, size=(n, 3)) * weight
    pure = PURE_DOF * s2 * weight
    num = lof.sum(axis=1).mean() / LOF_DOF.sum()
    den = pure.sum(axis=1).mean() / (PURE_DOF.sum() - counted.sum())
    return float(num / den)


def test_cost_limits():
    assert _variance_dof_cost(92, 0.0) == pytest.approx(2.0, abs=1e-6)  # estimated weight
    assert _variance_dof_cost(92, 3.0) == pytest.approx(0.0, abs=1e-6)  # the white part
    costs = [_variance_dof_cost(92, w) for w in (0.1, 0.5, 0.9, 1.0, 1.2)]
    assert all(a >= b for a, b in zip(costs, costs[1:]))  # more known white, less cost
    assert _variance_dof_cost(2, 0.0) == 0.0  # no mean of 1 / q: not counted


@pytest.mark.parametrize("white_share", [0.2, 0.55])
def test_the_cost_makes_the_f_mean_right_when_the_wander_dominates(white_share):
    # the physics units' steps: wander most of a gyro's step variance, half an accelerometer's
    cost = np.array([_variance_dof_cost(d, white_share) for d in PURE_DOF])
    assert np.all(cost > 1.9)
    se = 0.0015  # Monte Carlo sd of the ratio (40,000 draws of 114 dof)
    assert abs(_mean_f_ratio(white_share, cost) - 1.0) < 2.5 * se
    # one dof per variance, the former count, leaves the F optimistic by about 1 / d
    assert _mean_f_ratio(white_share, np.ones(3)) - 1.0 > 3 * se


def test_a_white_variance_costs_what_its_clipping_leaves():
    # the step variance is the known white part (no wander): the estimate is clipped at it
    # half the time, and the count of 2 for an estimated weight would make the F pessimistic
    cost = np.array([_variance_dof_cost(d, 1.0) for d in PURE_DOF])
    assert np.all((cost > 0.5) & (cost < 1.5))
    se = 0.0015
    assert abs(_mean_f_ratio(1.0, cost) - 1.0) < 2.5 * se
    assert _mean_f_ratio(1.0, np.full(3, 2.0)) - 1.0 < -2 * se
