"""Discovery's noise model can come from elsewhere (:meth:`NoiseModel.from_description`): a
description of the step-mean noise per channel and test group gives each step the sigma
sqrt(white^2 + instability^2), with the within-step white part measured on the unit; measured
independently of the repetitions it costs the tests no dof; the description of an estimated
model rebuilds that model exactly."""

from __future__ import annotations

import numpy as np

from calib_core.discovery import fit
from calib_core.discovery.noise import NoiseDescription, NoiseModel, SerialNoise
from calib_core.effects import CHANNELS

from conftest import discovery_unit


def test_an_estimated_noise_model_is_rebuilt_from_its_description():
    m = fit.joint_model(discovery_unit(41, n_reps=3))
    again = NoiseModel.from_description(m.g, m.noise.K, m.noise.description())
    np.testing.assert_array_equal(again.sigma, m.noise.sigma)
    np.testing.assert_array_equal(again.params, m.noise.params)
    assert again.serial == m.noise.serial


def test_a_measured_noise_gives_white_plus_instability_and_costs_no_dof():
    m = fit.joint_model(discovery_unit(42, n_reps=3))
    g = m.g
    K = np.tile(np.eye(3), (2, 1))
    inst = {ch: 1e-3 * (i + 1) for i, ch in enumerate(CHANNELS)}  # one per channel, every group
    rows = tuple((ch, grp, 100, np.nan, np.nan, inst[ch]) for ch in CHANNELS for grp in g.groups)
    measured = NoiseModel.from_description(g, K, NoiseDescription(rows, SerialNoise(np.zeros(6), np.ones(6))))
    # independent: the within-step scatter of each step mean, std / sqrt(count), per channel
    std = np.concatenate([np.stack([sm.gyro_std, sm.accel_std], 1) for sm in m.sessions]).reshape(-1, 6)
    count = np.concatenate([np.asarray(sm.count, float) for sm in m.sessions])
    white = std / np.sqrt(np.maximum(count, 1.0))[:, None]
    expected = np.sqrt(white**2 + np.array([inst[ch] for ch in CHANNELS]) ** 2)
    np.testing.assert_allclose(measured.sigma[g.real], expected, rtol=1e-12)
    assert not measured.params.any()  # measured elsewhere: no dof of the pure error spent
    assert m.noise.params.all()  # estimated from the repetitions: some spent on every channel
