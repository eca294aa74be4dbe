"""Issue 8 item 2 on the fits: property tests (hypothesis, derandomized) of
``calib_core.models.pipeline.calibrate_repetition`` on corrupted step means.

Whatever is done to a good session's step means (steps dropped at random, finite
perturbations of the means, references scaled, every step of an axis removed), the pipeline
either raises a DesignError (E_UNDETERMINED / E_IMPLAUSIBLE) or returns parameters that are
all finite with finite positive standard errors. And it never returns a calibration when the
design is rank-deficient, judged here independently of the estimators' own check (rank of the
+/- rate differences and of the multiposition [f_ref 1] matrix, with numpy's matrix_rank).

The reader-level fuzzing (bytes, table mutations, metadata) is in test_schemas_fuzz.py."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from calib_core.errors import DesignError
from calib_core.models.pipeline import calibrate_repetition
from calib_core.sim import protocols
from calib_core.sim import simulator as sim
from calib_core.steps import StepMeans

SETTINGS = dict(derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow])
CODES = {"E_UNDETERMINED", "E_IMPLAUSIBLE"}


def _base() -> tuple[sim.MimuTruth, StepMeans]:
    rng = np.random.default_rng(20261122)
    truth = sim.typical_truth(rng)
    return truth, sim.simulate_step_means(truth, protocols.default_session(), rng)


TRUTH, BASE = _base()
N = len(BASE)


def _replace(sm: StepMeans, **arrays) -> StepMeans:
    from dataclasses import replace

    return replace(sm, **arrays)


def gyro_design_rank(sm: StepMeans) -> tuple[int, int]:
    """(number of complete +/- multirate pairs, rank of their reference differences),
    pairing by (up axis, |rate|), written independently of xu2016.multirate_pairs."""
    groups: dict[tuple, dict[int, list[int]]] = {}
    for i in np.flatnonzero(sm.test == "multirate"):
        r = float(sm.rate_dps[i])
        if r != 0:
            groups.setdefault((str(sm.up_axis[i]), abs(r)), {1: [], -1: []})[int(np.sign(r))].append(i)
    dW = [sm.w_ref[p] - sm.w_ref[m] for g in groups.values() for p, m in zip(g[1], g[-1])]
    if not dW:
        return 0, 0
    return len(dW), int(np.linalg.matrix_rank(np.array(dW)))


def accel_design_rank(sm: StepMeans) -> tuple[int, int]:
    st_ = np.flatnonzero(sm.test == "multiposition")
    if not len(st_):
        return 0, 0
    X = np.hstack([sm.f_ref[st_], np.ones((len(st_), 1))])
    return len(st_), int(np.linalg.matrix_rank(X))


def check_outcome(sm: StepMeans):
    """Run the pipeline; return the DesignError or assert the result is clean. Any other
    exception fails the test (hypothesis reports the example)."""
    n_pairs, rank_g = gyro_design_rank(sm)
    n_pos, rank_a = accel_design_rank(sm)
    deficient = n_pairs < 4 or rank_g < 3 or n_pos < 5 or rank_a < 4
    try:
        fit = calibrate_repetition(sm)
    except DesignError as exc:
        assert exc.code in CODES, exc.code
        assert exc.reason  # names what went wrong
        return exc
    assert not deficient, (
        f"calibration from a rank-deficient design: {n_pairs} pairs "
        f"(rank {rank_g}), {n_pos} positions (rank {rank_a})"
    )
    for model, f in fit.calibration.fits.items():
        # the lever-arm fit leaves unobservable components NaN and names them in
        # ``undetermined`` (zhang2017); every other NaN would be silent
        named = set(getattr(f, "undetermined", ()) or ())
        for p in f.parameters():
            if p.name in named:
                assert model == "lever_arm" and not np.isfinite(p.value)
                continue
            assert np.isfinite(p.value), (model, p.name, p.value)
            assert np.isfinite(p.stderr) and p.stderr > 0, (model, p.name, p.stderr)
    assert np.isfinite(fit.residuals[["residual", "sigma"]].to_numpy(float)).all()
    return fit


@settings(max_examples=60, **SETTINGS)
@given(keep=st.lists(st.booleans(), min_size=N, max_size=N))
def test_dropping_random_steps_never_gives_nan_or_an_undetermined_calibration(keep):
    mask = np.array(keep)
    if not mask.any():
        mask[0] = True
    check_outcome(BASE.select(mask))


@settings(max_examples=60, **SETTINGS)
@given(
    axis=st.sampled_from(["x", "y", "z"]),
    tests=st.sampled_from([("multirate",), ("multiposition",), ("multirate", "multiposition")]),
    extra_drop=st.integers(0, 2**16),
)
def test_removing_every_step_of_an_axis_is_undetermined(axis, tests, extra_drop):
    """Every step with the axis up (+ and -) of the given tests is removed (plus a few random
    others): no rotation about that axis, or no +/-1 g along it. Must be a DesignError."""
    up = np.isin(BASE.up_axis, [f"+{axis}", f"-{axis}"]) & np.isin(BASE.test, tests)
    rng = np.random.default_rng(extra_drop)
    mask = ~up & (rng.random(N) > 0.1)
    sm = BASE.select(mask)
    out = check_outcome(sm)
    if "multirate" in tests:
        # no multirate step rotates about this axis: the gyro design must be deficient
        assert gyro_design_rank(sm)[1] < 3
        assert isinstance(out, DesignError) and out.code == "E_UNDETERMINED", out
    else:
        # without +/-axis up, the multiposition f_ref may still span 3-D through the tilted
        # positions; only a deficient design is required to fail
        if accel_design_rank(sm)[1] < 4:
            assert isinstance(out, DesignError) and out.code == "E_UNDETERMINED", out


@settings(max_examples=50, **SETTINGS)
@given(
    rows=st.lists(st.integers(0, N - 1), min_size=1, max_size=12, unique=True),
    channel=st.integers(0, 5),
    size=st.floats(-1e4, 1e4, allow_nan=False, allow_infinity=False),
    std_scale=st.floats(0.0, 100.0, allow_nan=False),
)
def test_finite_perturbations_of_step_means_give_an_error_or_finite_results(rows, channel, size, std_scale):
    gyro, accel = BASE.gyro.copy(), BASE.accel.copy()
    gs, as_ = BASE.gyro_std * std_scale, BASE.accel_std * std_scale
    target = gyro if channel < 3 else accel
    target[rows, channel % 3] += size
    check_outcome(_replace(BASE, gyro=gyro, accel=accel, gyro_std=gs, accel_std=as_))


@settings(max_examples=60, **SETTINGS)
@given(gyro_factor=st.floats(0.2, 5.0), accel_factor=st.floats(0.2, 5.0))
@example(gyro_factor=1.0, accel_factor=1.0)  # both branches surely exercised
@example(gyro_factor=1.1, accel_factor=0.9)
@example(gyro_factor=180 / np.pi, accel_factor=1.0)  # rad/s table read as deg/s
@example(gyro_factor=1.0, accel_factor=1 / 9.80665)  # m/s^2 references read as g
def test_scaled_references_are_refused_beyond_the_plausible_scale(gyro_factor, accel_factor):
    """References multiplied by c make the fitted K about c times the true one (K true within
    a few % of 1): beyond the guard's [0.75, 1.25] (with a 10 % margin for the truth's own
    scale error) the session must be E_IMPLAUSIBLE; well inside, it must calibrate."""
    sm = _replace(BASE, w_ref=BASE.w_ref * gyro_factor, f_ref=BASE.f_ref * accel_factor)
    out = check_outcome(sm)
    k_g = gyro_factor * np.diag(TRUTH.K_g)
    k_a = accel_factor * np.diag(TRUTH.K_a)
    outside = lambda k: (k < 0.75 * 0.97).any() or (k > 1.25 * 1.03).any()  # noqa: E731
    inside = lambda k: (k > 0.75 * 1.03).all() and (k < 1.25 * 0.97).all()  # noqa: E731
    if outside(k_g) or outside(k_a):
        assert isinstance(out, DesignError) and out.code == "E_IMPLAUSIBLE", out
        if outside(k_g):
            assert "gyro k_g" in out.reason, out.reason
        if outside(k_a):
            assert "accel k_a" in out.reason, out.reason
    elif inside(k_g) and inside(k_a):
        assert not isinstance(out, DesignError), out
        fits = out.calibration.fits
        assert np.allclose(np.diag(fits["gyro"].K), k_g, rtol=2e-3)
        assert np.allclose(np.diag(fits["accel"].K), k_a, rtol=2e-3)


def test_the_unperturbed_session_calibrates_to_the_truth():
    """The base of the properties is a good session (else every property is vacuous)."""
    fit = check_outcome(BASE)
    assert not isinstance(fit, DesignError)
    K = fit.calibration.fits["gyro"].K
    assert np.abs(K - TRUTH.K_g).max() < 1e-3


@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_one_sided_rates_about_an_axis_are_undetermined(axis):
    """Only the +rate steps about an axis are kept: no complete pair, no rotation difference
    about it (a deterministic case of the rank rule)."""
    up = np.isin(BASE.up_axis, [f"+{axis}", f"-{axis}"]) & (BASE.test == "multirate")
    mask = ~(up & (BASE.rate_dps < 0))
    out = check_outcome(BASE.select(mask))
    assert isinstance(out, DesignError) and out.code == "E_UNDETERMINED"
    assert axis in out.reason
