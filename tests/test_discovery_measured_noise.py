"""Model discovery on a measured noise model (issue 31 item 4,
:mod:`calib_core.discovery.measured_noise`):

- the step means' covariance derived from the processes' variograms (repetition mean
  removed) matches a Monte Carlo of :func:`calib_core.noise.synthesize` (the synthesis
  writes each process from its own physics): the steps' variance and lag-1 correlation
  within their sampling error; the serial model fitted to it (what discovery whitens with)
  gives the same variance and lag-1 correlation to a few per cent;
- a clean physics-simulated unit whose noise is drawn from a measured model, with that model
  in discovery's null: no misfit, no dof spent on the noise, the JSON says "measured";
- in the nightly, a unit with a noise recording hands its model to discovery; a unit
  without one keeps the noise estimated from its repetitions."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from calib_core.discovery import diagnose_unit
from calib_core.discovery.measured_noise import (
    ESTIMATED_SOURCE,
    MeasuredNoise,
    _centre,
    centred_step_covariance,
    step_noise_description,
    white_step_variance,
)
from calib_core.noise import ChannelNoise, NoiseModel, synthesize

RATE = 20.0
COUNT = 50  # 2.5 s steps after settling
STARTS = np.arange(40) * 64 + 14  # 3.2 s apart, as the default protocol's steps
SPAN = int(STARTS[-1] + COUNT + 10)

CHANNELS = {
    # the real MPU-6050 gyro y (white, bias instability, a 38 Hz line, 1 LSB resolution)
    # with its bias instability tripled: a flicker wander of the step means
    "flicker_line": ChannelNoise(
        "deg/s",
        {"white": 0.011, "bias_instability": 0.008},
        periodic=((7.3, 0.02),),
        resolution=0.0076,
    ),
    # a random walk, a Gauss-Markov wander and a quantization on top of the white
    "walk_markov_quant": ChannelNoise(
        "deg/s",
        {"white": 0.011, "random_walk": 0.001, "quantization": 4e-4},
        gauss_markov=(0.004, 15.0),
    ),
}


def _step_means(ch: ChannelNoise, reps: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    model = NoiseModel(RATE, SPAN / RATE, {"gx": ch})
    Y = np.empty((reps, len(STARTS)))
    for r in range(reps):
        x = synthesize(model, SPAN, RATE, rng)["gx"]
        Y[r] = [x[s : s + COUNT].mean() for s in STARTS]
    return Y - Y.mean(axis=1, keepdims=True)


@pytest.mark.parametrize("name", sorted(CHANNELS))
def test_step_mean_covariance_matches_a_monte_carlo_of_the_synthesis(name):
    ch = CHANNELS[name]
    C = centred_step_covariance(ch, STARTS, np.full(len(STARTS), COUNT), RATE, SPAN)
    Y = _step_means(ch, 600, seed=311)
    var_r = np.mean(Y**2, axis=1)  # per record: independent samples of the statistics
    lag_r = np.mean(Y[:, 1:] * Y[:, :-1], axis=1)
    var_mc, var_se = var_r.mean(), var_r.std() / np.sqrt(len(Y))
    var_th = float(np.mean(np.diag(C)))
    assert abs(var_th - var_mc) < 4.0 * var_se
    rho_th = float(np.mean(np.diag(C, 1))) / var_th
    rho_mc, rho_se = lag_r.mean() / var_mc, (lag_r / var_mc).std() / np.sqrt(len(Y))
    assert abs(rho_th - rho_mc) < 4.0 * rho_se + 0.01
    # the wander is there to be seen: not white noise
    white = white_step_variance(ch, np.array([COUNT]), RATE)[0]
    assert var_th > 1.2 * white * (1 - 1 / len(STARTS))
    assert rho_th > 0.05


class _Grid:
    """The fields of a UnitGrid that the description reads: one repetition, one group."""

    def __init__(self):
        n = len(STARTS)
        self.real = np.ones((1, n), bool)
        self.t = ((STARTS + (COUNT - 1) / 2.0) / RATE)[None, :]
        self.count = np.full((1, n), float(COUNT))
        self.gcode = np.zeros((1, n), np.int64)
        self.groups = ["rate"]


@pytest.mark.parametrize("name", sorted(CHANNELS))
def test_the_fitted_serial_model_gives_the_monte_carlo_variance_and_lag1(name):
    ch = CHANNELS[name]
    grid = _Grid()
    model = NoiseModel(RATE, 900.0, {c: ch for c in ("gx", "gy", "gz", "ax", "ay", "az")})
    desc = step_noise_description(model, grid, RATE)
    assert not desc.estimated and desc.white_from_rows
    sigma = desc.rows[0][3]
    lam, tau = desc.serial.lam[0], desc.serial.tau_s[0]
    t = grid.t[0]
    S = sigma**2 * np.where(
        np.eye(len(t), dtype=bool), 1.0, lam * np.exp(-np.abs(t[:, None] - t[None, :]) / tau)
    )
    M = _centre(S)
    Y = _step_means(ch, 600, seed=312)
    var_mc = np.mean(Y**2)
    rho_mc = np.mean(Y[:, 1:] * Y[:, :-1]) / var_mc
    var_m = float(np.mean(np.diag(M)))
    assert abs(var_m / var_mc - 1.0) < 0.05
    assert abs(float(np.mean(np.diag(M, 1))) / var_m - rho_mc) < 0.05


def _measured_unit(seed: int):
    from calib_core.sim import protocols
    from tools.discovery_measured_noise import quiet_unit, step_means_with_noise

    gyro = ChannelNoise("deg/s", {"white": 0.011, "bias_instability": 0.0027}, periodic=((37.99, 0.017),))
    accel = ChannelNoise("g", {"white": 5e-5, "bias_instability": 4e-5})
    model = NoiseModel(
        100.0, 449.0, {c: gyro if c[0] == "g" else accel for c in ("gx", "gy", "gz", "ax", "ay", "az")}
    )
    rng = np.random.default_rng(seed)
    return step_means_with_noise(quiet_unit(rng), model, protocols.default_session(), rng, "U001"), model


def test_a_clean_unit_with_its_measured_noise_in_the_null_fits_and_says_so():
    sessions, model = _measured_unit(3101)
    d = diagnose_unit(sessions, tables=False, measured_noise=MeasuredNoise(model, "recording static"))
    assert not d.misfit and not d.effects
    assert d.noise_source == "measured: recording static"
    assert d.to_dict()["noise_source"] == "measured: recording static"
    assert diagnose_unit(sessions, tables=False).noise_source == ESTIMATED_SOURCE


def test_a_measured_noise_costs_no_dof_and_sets_the_step_sigma():
    from calib_core.discovery import fit

    sessions, model = _measured_unit(3102)
    m = fit.joint_model(sessions, measured=MeasuredNoise(model, "recording static"))
    assert not m.noise.params.any()
    # every step's sigma: the gyro's white step-mean variance N^2 / T (N = 0.011 deg/s/sqrt(Hz),
    # T the averaged duration) plus the wander's
    white = 0.011 / np.sqrt(m.g.count[m.g.real] / sessions[0].sample_rate_hz)
    np.testing.assert_allclose(
        m.noise.sigma[..., 0][m.g.real], np.hypot(white, m.noise.rows[0][5]), rtol=1e-12
    )
    assert m.noise.serial.lam[:3].min() > 0  # the flicker wander correlates the gyro steps


def test_the_nightly_hands_a_noise_recording_to_discovery(tmp_path):
    from flows import runtime

    runtime.ensure_environment()
    from flows.fleet_sim import simulate_fleet
    from flows.unit_pipeline import calibrate_batch
    from schemas.dataset import find_sessions
    from schemas.unit_plan import plan_unit_jobs

    simulate_fleet(tmp_path, lots=1, units=2, reps=3, seed=31, sample_rate_hz=10.0, noise_recording_s=400.0)
    units = sorted(p.name.split("=")[1] for p in (tmp_path / "lot=L01").glob("unit=*"))
    shutil.rmtree(tmp_path / "lot=L01" / f"unit={units[1]}" / "noise")  # this one: no recording
    refs, _ = find_sessions(tmp_path)
    jobs, _, _ = plan_unit_jobs(refs, {})
    results = {r.unit: r for r in calibrate_batch(jobs, run_discovery=True)}
    with_rec, without = results[units[0]], results[units[1]]
    assert with_rec.diagnosis["noise_source"] == "measured: recording static"
    assert with_rec.outcome.noise.source == "recording static"
    assert without.diagnosis["noise_source"] == ESTIMATED_SOURCE
    assert without.outcome.noise.source.startswith("static steps")


def test_a_measured_model_without_noise_on_a_channel_is_refused_by_name():
    silent = {c: ChannelNoise("deg/s", {"white": 0.0 if c == "gy" else 0.01}) for c in ("gx", "gy", "gz")}
    silent.update({c: ChannelNoise("g", {"white": 1e-4}) for c in ("ax", "ay", "az")})
    with pytest.raises(ValueError, match="channel gy has no noise"):
        step_noise_description(NoiseModel(RATE, 900.0, silent), _Grid(), RATE)
