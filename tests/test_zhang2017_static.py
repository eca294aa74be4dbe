"""zhang2017 static model: 15 <-> 12 parameter conversions, recovery on simulated units,
standard errors against Monte Carlo spread."""

import numpy as np
import pytest

from calib_core.errors import DesignError
from calib_core.models.zhang2017 import (
    C_from_angles,
    affine_from_parts,
    affine_to_static,
    angles_from_C,
    fit_accel_static,
    static_to_affine,
)
from calib_core.results import FitResult
from calib_core.sim import protocols
from calib_core.sim.simulator import simulate_step_means

from conftest import PAPER_ANGLES, PAPER_NOISE, paper_unit, random_unit


def test_angles_to_cosines_matches_definition():
    # theta_ij is the angle between sensitive axis i and body axis j: c_i . e_j = cos theta_ij
    C = C_from_angles(PAPER_ANGLES)
    assert np.allclose(np.linalg.norm(C, axis=0), 1.0, atol=1e-15)
    assert abs(C[0, 0] - np.cos(np.radians(0.75997))) < 1e-8
    assert abs(C[1, 0] - np.cos(np.radians(90.71425))) < 1e-8  # x accelerometer along body y
    # without normalisation the published angles come back exactly
    assert np.allclose(
        angles_from_C(C_from_angles(PAPER_ANGLES, normalise=False)), PAPER_ANGLES, rtol=0, atol=1e-9
    )


@pytest.mark.parametrize("seed", range(20))
def test_round_trip_15_12_machine_precision(seed):
    rng = np.random.default_rng(seed)
    u = random_unit(rng, tilt_deg=rng.uniform(0.01, 10.0)) if seed else paper_unit()
    K_a, f0 = affine_from_parts(u.scale, u.bias, u.C)
    # independent check of the affine form: f = K_a A + f0 inverts A = k (C^T f) + u0
    f = rng.normal(size=3)
    A = u.scale * (u.C.T @ f) + u.bias
    assert np.allclose(K_a @ A + f0, f, rtol=0, atol=1e-12)
    k, u0, C = affine_to_static(K_a, f0)
    assert np.max(np.abs(k - u.scale) / u.scale) < 1e-14
    assert np.max(np.abs(u0 - u.bias)) < 1e-14 * 10
    assert np.max(np.abs(C - u.C)) < 1e-14
    # and back again from a random affine form
    K2 = np.eye(3) * rng.uniform(2.4, 2.6) + rng.normal(0, 0.05, (3, 3))
    f02 = rng.normal(0, 6, 3)
    k, u0, C = affine_to_static(K2, f02)
    K3, f03 = affine_from_parts(k, u0, C)
    assert np.max(np.abs(K3 - K2)) < 1e-14 * 10 and np.max(np.abs(f03 - f02)) < 1e-13


def _fit(u, steps, rng, **noise):
    return fit_accel_static(simulate_step_means(u.to_mimu_truth(**(noise or PAPER_NOISE)), steps, rng))


def test_static_fit_recovers_paper_unit():
    u = paper_unit()
    fit = _fit(u, protocols.zhang2017_session(), np.random.default_rng(3))
    assert isinstance(fit, FitResult) and fit.model == "accel_static"
    assert np.max(np.abs(fit.angles_deg - u.angles_deg)) < 0.01
    assert np.all(np.abs(fit.scale - u.scale) < 5 * fit.scale_stderr)
    assert np.all(np.abs(fit.bias - u.bias) < 5 * fit.bias_stderr)
    # the affine form reproduces +/-1 g inputs (f0 alone is -6 g here: compare outputs)
    K_a, f0 = static_to_affine(fit)
    f_in = np.vstack([np.eye(3), -np.eye(3), [[0.6, -0.64, 0.48]]])
    A = f_in @ (u.scale[:, None] * u.C.T).T + u.bias
    assert np.max(np.abs(A @ K_a.T + f0 - f_in)) < 5e-5
    d = fit.to_dict()
    assert np.array(d["angles_deg"]).shape == (3, 3) and len(d["scale"]) == 3
    assert np.array(d["stderr"]["angles_deg"]).shape == (3, 3)
    assert d["units"] == {"scale": "V/g", "bias": "V", "angles_deg": "deg"}
    names = [p.name for p in fit.parameters()]
    assert len(names) == 15 and "theta_xy" in names and "k_z" in names and "u0_x" in names


def test_six_position_alone_and_multiposition():
    u = random_unit(np.random.default_rng(7))
    six = protocols.to_frame(protocols.zhang2017_six_position())
    fit = _fit(u, six, np.random.default_rng(8))
    assert fit.n_steps == 6 and fit.dof == 6
    assert np.max(np.abs(fit.angles_deg - u.angles_deg)) < 0.01
    # xu2016's multiposition test (33 steps) works the same way
    mp = protocols.to_frame(protocols.xu2016_multiposition(duration_s=30.0))
    fit = _fit(u, mp, np.random.default_rng(9))
    assert fit.n_steps == 33
    assert np.max(np.abs(fit.angles_deg - u.angles_deg)) < 0.01


def test_too_few_or_degenerate_static_steps():
    u = random_unit(np.random.default_rng(1))
    rows = protocols.zhang2017_six_position()[:4]
    with pytest.raises(DesignError) as e:
        _fit(u, protocols.to_frame(rows), np.random.default_rng(0))
    assert e.value.code == "E_TOO_FEW_STATIC_STEPS"
    # five steps but only +/- x and +/- y: the z column is not determined
    rows = protocols.zhang2017_six_position()[:4] + protocols.zhang2017_six_position()[:1]
    with pytest.raises(DesignError) as e:
        _fit(u, protocols.to_frame(rows), np.random.default_rng(0))
    assert e.value.code == "E_STATIC_RANK"
