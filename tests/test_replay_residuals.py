"""Replay: residual = K (measured - predicted raw) on every channel of every step, and its
noise estimated from the data (within-step scatter + repetition scatter), checked against
the simulator's truth."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from calib_core.calibration import Calibration, TermValue
from calib_core.discovery.replay import REPLAY_COLUMNS, estimate_noise, replay_session, replay_unit
from calib_core.effects import get_effect
from calib_core.sim import protocols
from calib_core.sim import simulator as sim
from calib_core.steps import SessionKey

STEPS = protocols.default_session()


def truth_calibration(truth, terms=()):
    return Calibration(K_g=truth.K_g, w0=truth.w0, K_a=truth.K_a, f0=truth.f0, terms=terms)


def noiseless(truth):
    return replace(
        truth,
        gyro_noise_dps=1e-12,
        gyro_bias_instability_dps=0.0,
        accel_noise_g=1e-12,
        accel_bias_instability_g=0.0,
    )


def test_true_calibration_replays_every_channel_to_zero():
    rng = np.random.default_rng(1)
    lever = np.array([3.0, -2.0, 1.0, 0, 0, 0, 0, 0, 4.0])
    truth = noiseless(sim.typical_truth(rng)).with_effects((get_effect("lever_arm"), lever))
    sm = sim.simulate_step_means(truth, STEPS, rng)
    table = replay_session(truth_calibration(truth, (TermValue("lever_arm", lever),)), sm)
    assert list(table.columns) == list(REPLAY_COLUMNS)
    assert len(table) == 6 * len(sm)
    assert np.abs(table["residual"]).max() < 1e-9
    # without the lever arm the accelerometers are wrong during rotation only
    bare = replay_session(truth_calibration(truth), sm)
    acc_rot = bare[bare.channel.isin(["ax", "ay", "az"]) & (bare.rate_dps != 0)]
    acc_static = bare[bare.channel.isin(["ax", "ay", "az"]) & (bare.rate_dps == 0)]
    assert np.abs(acc_rot["residual"]).max() > 1e-3
    assert np.abs(acc_static["residual"]).max() < 1e-9


def test_residual_is_the_physical_error_of_a_bias_offset():
    rng = np.random.default_rng(2)
    truth = noiseless(sim.typical_truth(rng))
    sm = sim.simulate_step_means(truth, STEPS, rng)
    offset = np.array([0.2, -0.1, 0.05, 1e-3, -2e-3, 3e-3])
    # a calibration whose biases are too large by offset outputs reference + offset
    cal = replace(truth_calibration(truth), w0=truth.w0 + offset[:3], f0=truth.f0 + offset[3:])
    table = replay_session(cal, sm)
    for i, ch in enumerate(("gx", "gy", "gz", "ax", "ay", "az")):
        np.testing.assert_allclose(table.loc[table.channel == ch, "residual"], offset[i], atol=1e-9)


def test_noise_estimate_matches_the_truth_and_sees_bias_instability():
    """step_sd from the repetition scatter ~ sqrt(white^2/count + instability^2); white noise
    alone would underestimate it 3x."""
    rng = np.random.default_rng(3)
    truth = sim.typical_truth(
        rng,
        gyro_noise_dps=0.05,
        gyro_bias_instability_dps=0.01,
        gyro_bias_repeatability_dps=0.05,
        accel_noise_g=1e-3,
        accel_bias_instability_g=1e-4,
        accel_bias_repeatability_g=1e-3,
    )
    sessions = []
    for r in range(1, 7):
        tr = sim.draw_repetition_truth(truth, rng)
        sessions.append(sim.simulate_step_means(tr, STEPS, rng, key=SessionKey("L", "U", r)))
    cal = truth_calibration(truth)  # turn-on biases differ per repetition: removed per rep
    table = replay_unit(cal, sessions)
    noise = estimate_noise(table)
    count = sessions[0].count[0]
    expect_g = np.sqrt(0.05**2 / count + 0.01**2)
    expect_a = np.sqrt(1e-6 / count + 1e-8)
    tab = noise.table
    gyro = tab[tab.channel.str.startswith("g")]
    acc = tab[tab.channel.str.startswith("a")]
    # relative sd of a variance estimate with >= 100 dof is < 15 %; sd within 10 % per group
    assert np.all(np.abs(gyro.step_sd / expect_g - 1) < 0.15), gyro
    assert np.all(np.abs(acc.step_sd / expect_a - 1) < 0.15), acc
    np.testing.assert_allclose(gyro.white_sd, 0.05 / np.sqrt(count), rtol=0.05)
    assert np.all(gyro.instability_sd > 0.7 * 0.01)
    assert noise.from_repetitions
    # sigma column carries it; normalised residuals have unit rms (minus the per-rep bias)
    gyro_rows = table.channel.str.startswith("g")
    assert np.all(table.sigma[gyro_rows] > 2.5 * table.sigma_white[gyro_rows])
    assert np.all(table.sigma[~gyro_rows] > 1.4 * table.sigma_white[~gyro_rows])
    g = table[table.channel == "gx"]
    zc = (g.residual - g.groupby("rep").residual.transform("mean")) / g.sigma
    assert 0.85 < np.sqrt(np.mean(zc**2)) < 1.15


def test_single_repetition_falls_back_to_white_noise():
    rng = np.random.default_rng(4)
    truth = sim.typical_truth(rng)
    sm = sim.simulate_step_means(truth, STEPS, rng)
    table = replay_unit(truth_calibration(truth), [sm])
    assert not estimate_noise(table).from_repetitions
    np.testing.assert_allclose(table.sigma, table.sigma_white)


def test_xu2016_replay_shows_what_the_difference_method_cannot_see():
    """A quadratic z gyro error cancels in xu2016's +/- differences (its K is unbiased) but
    the replay of every step shows it, growing with rate; a clean unit replays to noise."""
    from calib_core.discovery.replay import replay_xu2016, summarise_residuals

    def unit(effects, seed):
        rng = np.random.default_rng(seed)
        truth = sim.typical_truth(
            rng,
            gyro_noise_dps=0.05,
            gyro_bias_instability_dps=0.01,
            accel_noise_g=1e-3,
            accel_bias_instability_g=1e-4,
        )
        truth = truth.with_effects(*effects)
        return [
            sim.simulate_step_means(
                sim.draw_repetition_truth(truth, rng), STEPS, rng, key=SessionKey("L", "U", r)
            )
            for r in (1, 2, 3)
        ]

    quad = (get_effect("gyro_scale_nonlinearity"), [0, 0, 0.1, 0, 0, 0])  # 1.3 deg/s at 3600
    s = summarise_residuals(replay_xu2016(unit([quad], 8))).set_index(["channel", "test"])
    assert s.loc[("gz", "multirate"), "rms_z"] > 20
    assert s.loc[("gx", "multirate"), "rms_z"] < 1.5
    clean = summarise_residuals(replay_xu2016(unit([], 9))).set_index(["channel", "test"])
    assert clean.loc[("gz", "multirate"), "rms_z"] < 1.5
