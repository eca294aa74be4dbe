"""A unit's noise from its sessions' static steps (no long recording): measured on the
samples the unit pipeline kept from its one read of each session, the Allan deviation of
the six channels together, the quantization + white fit of the six together.

- on a simulated lot without recordings (20 Hz, 2 repetitions, one unit at three times the
  lot's angle random walk): every unit's white coefficients match the simulator's truth and
  their intervals cover it on most channels; the noisy unit, and no other, is flagged;
- the pipeline reads no session a second time for the noise, and its model is the one
  measured by reading the sessions again;
- the vectorised Allan deviation agrees with allantools (``allan_curve``) and the stacked
  fit with ``fit_allan`` (scipy's NNLS), channel by channel, on records of known noise
  types; ``nnls_stack`` with scipy's NNLS."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from scipy import optimize

from calib_core.linalg import nnls_stack
from calib_core.noise.allan import allan_curve, allan_curves
from calib_core.noise.fit import Term, fit_allan, fit_allan_stack
from calib_core.noise.units import G0
from calib_core.noise_fleet import judge_noise
from calib_core.sim.simulator import MimuTruth
from flows.fleet_sim import simulate_fleet
from flows.unit_pipeline import calibrate_batch
from schemas.dataset import find_sessions
from schemas.unit_noise import measure_unit_noise
from schemas.unit_plan import plan_unit_jobs

RATE_HZ = 20.0


@pytest.fixture(scope="module")
def lot(tmp_path_factory):
    root = tmp_path_factory.mktemp("staticnoise")
    manifest = simulate_fleet(
        root, lots=1, units=8, reps=2, seed=32, sample_rate_hz=RATE_HZ, noisy_units=1, noise_factor=3.0
    )
    refs, errors = find_sessions(root)
    assert refs and not errors
    jobs, _, _ = plan_unit_jobs(refs, {})
    import schemas.reader

    reads = []
    original = schemas.reader.read_session

    def counting(ref):  # what a second read (schemas.unit_noise.static_segments) would call
        reads.append(ref.key)
        return original(ref)

    schemas.reader.read_session = counting
    try:
        results = calibrate_batch(jobs, run_discovery=False)
    finally:
        schemas.reader.read_session = original
    rows = pd.DataFrame(
        [{**r, "lot": ur.lot, "unit": ur.unit} for ur in results for r in ur.outcome.noise.coefficient_rows]
    )
    return {
        "manifest": manifest,
        "noisy": manifest["noise"]["noisy_units"][0]["unit"],
        "jobs": jobs,
        "results": results,
        "rows": rows,
        "second_reads": reads,
    }


def test_every_unit_is_measured_on_its_static_steps(lot):
    assert lot["rows"]["source"].str.startswith("static steps").all()
    assert set(lot["rows"]["unit"]) == {u["unit"] for u in lot["manifest"]["units"]}


def test_white_coefficients_match_the_simulated_truth(lot):
    truth = MimuTruth()  # the lot's white noise per sample (the population model's)
    rows = lot["rows"][lot["rows"]["coefficient"] == "white"]
    inside = []
    for unit, g in rows.groupby("unit"):
        factor = 3.0 if unit == lot["noisy"] else 1.0
        sd = {c: truth.gyro_noise_dps * factor for c in ("gx", "gy", "gz")}
        sd |= {c: truth.accel_noise_g * G0 for c in ("ax", "ay", "az")}  # m/s^2
        g = g.set_index("channel")
        assert len(g) == 6
        for ch, s in sd.items():
            expected = s / math.sqrt(RATE_HZ) * 60.0  # deg/sqrt(h), m/s/sqrt(h)
            assert g.loc[ch, "value"] == pytest.approx(expected, rel=0.10), (unit, ch)
            inside.append(g.loc[ch, "lo"] <= expected <= g.loc[ch, "hi"])
    assert np.mean(inside) >= 0.8, np.mean(inside)


def test_the_noisy_unit_and_no_other_is_flagged(lot):
    _, flags, _ = judge_noise(lot["rows"])
    assert {f.unit for f in flags} == {lot["noisy"]}
    assert {f.parameter.split(".")[1] for f in flags} == {"white"}


def test_no_session_is_read_again_and_the_model_is_the_one_read_again_gives(lot):
    assert lot["second_reads"] == []
    for job, ur in zip(lot["jobs"][:3], lot["results"][:3]):
        good = [(s.key, s.path) for s in ur.outcome.sessions if s.succeeded]
        again, _ = measure_unit_noise(job.refs[0].path.parent, ur.lot, ur.unit, ur.outcome.applied, good)
        for name in ("coefficient_rows", "allan_rows"):
            pd.testing.assert_frame_equal(
                pd.DataFrame(getattr(again, name)), pd.DataFrame(getattr(ur.outcome.noise, name))
            )


def _records(rng, n=6000):
    """Six channels of known noise types: white, quantised white, white + random walk,
    blue (differenced white: the quantization slope), a constant, a large offset."""
    return np.column_stack(
        [
            rng.normal(size=n),
            np.round(rng.normal(size=n) * 2.0) / 2.0,
            rng.normal(size=n) + 0.05 * np.cumsum(rng.normal(size=n)),
            np.diff(rng.normal(size=n + 1)) + 0.1 * rng.normal(size=n),
            np.full(n, 3.0),
            1e3 + 1e-3 * rng.normal(size=n),
        ]
    )


def test_allan_curves_agree_with_allantools_channel_by_channel():
    rng = np.random.default_rng(4)
    m = 2 ** np.arange(8)
    for _ in range(3):
        X = _records(rng)
        for i, got in enumerate(allan_curves(X, 50.0, m)):
            ref = allan_curve(X[:, i], 50.0, m)
            np.testing.assert_array_equal(got.tau_s, ref.tau_s)
            np.testing.assert_array_equal(got.alpha, ref.alpha)
            np.testing.assert_array_equal(got.edf, ref.edf)
            for f in ("adev", "adev_lo", "adev_hi"):
                np.testing.assert_allclose(getattr(got, f), getattr(ref, f), rtol=1e-9, atol=1e-300)


def test_the_stacked_fit_is_fit_allan_channel_by_channel():
    rng = np.random.default_rng(5)
    terms = (Term("quantization"), Term("white"))
    for _ in range(3):
        X = _records(rng)[:, [0, 1, 2, 3, 5]]
        curves = allan_curves(X, 50.0, 2 ** np.arange(6))
        for got, curve in zip(fit_allan_stack(curves, terms), curves):
            ref = fit_allan(curve, terms)
            np.testing.assert_allclose(got.c, ref.c, rtol=1e-8, atol=1e-12 * ref.c.max())
            np.testing.assert_allclose(got.c_se, ref.c_se, rtol=1e-8)
            np.testing.assert_allclose(got.model_avar, ref.model_avar, rtol=1e-8)
            assert got.dof == ref.dof and got.fraction_within_ci == ref.fraction_within_ci
            assert got.chi2 == pytest.approx(ref.chi2, rel=1e-8)


def test_nnls_stack_is_scipys_nnls():
    rng = np.random.default_rng(6)
    A = rng.normal(size=(200, 7, 3))
    b = rng.normal(size=(200, 7))
    got = nnls_stack(A, b)
    ref = np.array([optimize.nnls(a, y)[0] for a, y in zip(A, b)])
    assert (got >= 0).all() and np.any(ref == 0) and np.any(np.all(ref > 0, axis=1))
    np.testing.assert_allclose(got, ref, atol=1e-10)


def test_static_steps_are_each_static_steps_samples_after_settling(lot):
    from schemas.reader import read_session
    from schemas.unit_noise import STATIC_TESTS, static_steps

    data = read_session(lot["jobs"][0].refs[0])
    got = static_steps(data)
    steps = data.steps
    expected, lengths = [], []
    for _, s in steps.iterrows():  # step by step, as the protocol defines them
        if s["test"] not in STATIC_TESTS or s["rate_dps"] != 0:
            continue
        idx = np.flatnonzero(data.step == s["step"])
        if len(idx):
            idx = idx[data.t[idx] - data.t[idx[0]] >= s["settle_s"] - 1e-6]
            expected.append(idx)
            lengths.append(len(idx))
    rows = np.concatenate(expected)
    assert got.lengths == tuple(lengths) and len(lengths) > 30
    np.testing.assert_array_equal(got.gyro, data.gyro[rows])
    np.testing.assert_array_equal(got.accel, data.accel[rows])
    assert got.rate_hz == RATE_HZ


def test_rows_of_runs_are_the_rows_fancy_indexing_gives():
    from schemas.unit_noise import _rows_at

    rng = np.random.default_rng(5)
    block = rng.normal(size=(6, 1000))
    a = block[:3].T  # a column-major view, as a session's samples are held
    for idx in (
        np.arange(0),
        np.arange(5),
        np.r_[3:10, 20:30, 29:40, 5:8],  # runs, a repeated row, a run backwards in the block
        np.arange(999, -1, -1),  # one row a run: fancy indexing
        rng.integers(0, 1000, 600),
    ):
        rows = _rows_at(a, idx)
        assert np.array_equal(rows, a[idx]) and rows.flags.c_contiguous and rows.dtype == a.dtype
