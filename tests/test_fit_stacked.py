"""The repetitions of a unit fitted together (issue 7, fourth round) give what each session
gives alone, bit for bit: fits, standard errors, warnings, errors and tables.

``calibrate_repetitions`` stacks the sessions that share a step layout; a session that fails
or warns from a stacked fit sends its group back to one session at a time. Seeded
simulations: a clean group, a group with one implausible session, a session with a step
missing (its own layout), untilted dynamic steps (undetermined lever arms, warnings), and a
unit of files with a damaged session through ``flows.unit_pipeline.calibrate_sessions``.
"""

from __future__ import annotations

import pickle
from dataclasses import fields, is_dataclass, replace

import numpy as np
import pytest

from calib_core.errors import DesignError
from calib_core.linalg import solve_lstsq, solve_lstsq_stack
from calib_core.models.pipeline import _same_layout, calibrate_repetition, calibrate_repetitions
from calib_core.sim import protocols
from calib_core.steps import StepMeans

from conftest import STEPS_WITH_VERIFICATION, unit_step_means


def _assert_same(a, b, path="") -> None:
    """Exact equality of nested results (arrays by value and dtype, floats bit for bit)."""
    if is_dataclass(a) and not isinstance(a, type):
        assert type(a) is type(b), path
        for f in fields(a):
            _assert_same(getattr(a, f.name), getattr(b, f.name), f"{path}.{f.name}")
    elif isinstance(a, dict):
        assert list(a) == list(b), path
        for k in a:
            _assert_same(a[k], b[k], f"{path}[{k!r}]")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _assert_same(x, y, f"{path}[{i}]")
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape, path
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), path
    else:
        assert type(a) is type(b) and (a == b or (a != a and b != b)), path


def _assert_fit_equal(together, alone) -> None:
    _assert_same(together.calibration, alone.calibration)
    for attr in ("compensation", "residuals"):
        a, b = getattr(together, attr), getattr(alone, attr)
        assert list(a.columns) == list(b.columns)
        for c in a.columns:
            assert a[c].dtype == b[c].dtype, c
            np.testing.assert_array_equal(a[c].to_numpy(), b[c].to_numpy(), err_msg=c)


def _alone(sm: StepMeans):
    try:
        return calibrate_repetition(sm)
    except Exception as exc:  # noqa: BLE001 - compared with what the stacked call gives
        return exc


def _check_against_alone(sms: list[StepMeans]) -> list:
    together = calibrate_repetitions(sms)
    for t, sm in zip(together, sms):
        a = _alone(sm)
        if isinstance(a, Exception):
            assert type(t) is type(a) and str(t) == str(a)
            assert t.code == a.code and t.undetermined == a.undetermined
        else:
            _assert_fit_equal(t, a)
    return together


def test_stacked_group_equals_each_session_alone():
    sms = unit_step_means()
    assert _same_layout(sms) == [[0, 1, 2, 3, 4]]
    out = _check_against_alone(sms)
    assert all(not f.calibration.warnings for f in out)
    # the sessions' numbers differ (no session's result leaked into another's)
    k = [f.calibration.fits["gyro"].K[0, 0] for f in out]
    assert len(set(k)) == len(k)
    assert len({f.calibration.fits["lever_arm"].stderr[1, 2] for f in out}) == len(out)


def test_each_batched_fit_equals_its_per_session_fit():
    from calib_core.models import xu2016, zhang2017

    sms = unit_step_means(n=4, seed=21)
    pairs = [
        (xu2016.fit_gyro_multirate_stack, xu2016.fit_gyro_multirate),
        (xu2016.fit_accel_multiposition_stack, xu2016.fit_accel_multiposition),
        (xu2016.fit_gyro_traditional_stack, xu2016.fit_gyro_traditional),
        (xu2016.fit_accel_traditional_stack, xu2016.fit_accel_traditional),
        (zhang2017.fit_accel_static_stack, zhang2017.fit_accel_static),
    ]
    for batched, alone in pairs:
        for together, sm in zip(batched(sms), sms):
            _assert_same(together, alone(sm))
    statics = zhang2017.fit_accel_static_stack(sms)
    inputs = zhang2017.lever_arm_inputs_stack(sms, statics)
    for projection in zhang2017.PROJECTIONS:
        for together, sm, st in zip(
            zhang2017.fit_lever_arm_from_stack(inputs, projection=projection), sms, statics
        ):
            _assert_same(together, zhang2017.fit_lever_arm(sm, st, projection=projection))


def test_one_implausible_session_fails_alone_and_the_rest_is_unchanged():
    sms = unit_step_means(seed=8)
    sms[2] = replace(sms[2], gyro=sms[2].gyro * 2.0)  # K_g diagonal ~0.5: not a sensor
    out = _check_against_alone(sms)
    assert isinstance(out[2], DesignError) and out[2].code == "E_IMPLAUSIBLE"
    assert "k_g11" in str(out[2])
    assert all(not isinstance(out[i], Exception) for i in (0, 1, 3, 4))


def test_a_session_with_a_step_missing_has_its_own_layout():
    sms = unit_step_means(seed=9)
    keep = np.ones(len(sms[1]), bool)
    keep[np.flatnonzero(sms[1].test == "dynamic")[3]] = False  # as a saturated step
    sms[1] = sms[1].select(keep)
    assert _same_layout(sms) == [[0, 2, 3, 4], [1]]
    _check_against_alone(sms)


def test_undetermined_lever_arms_are_a_protocol_note_not_a_warning():
    steps = protocols.to_frame(
        protocols.xu2016_multirate()
        + protocols.xu2016_multiposition()
        + protocols.dynamic_steps(tilted=False)
    )
    sms = unit_step_means(seed=10, steps=steps)
    out = _check_against_alone(sms)
    for f in out:
        assert any(n.startswith("P_LEVER_ARM_UNOBSERVED") for n in f.calibration.protocol_notes)
        assert not any("LEVER_ARM" in w for w in f.calibration.warnings)
        assert np.isnan(f.calibration.fits["lever_arm"].lever_arm_mm).any()


def test_raw_units_and_no_stationary_steps():
    steps = STEPS_WITH_VERIFICATION[STEPS_WITH_VERIFICATION["test"] != "stationary"].reset_index(drop=True)
    sms = unit_step_means(seed=12, steps=steps)
    sms = [replace(sm, gyro_unit="LSB") for sm in sms]  # the Table 3 'uncompensated' is NaN
    out = _check_against_alone(sms)
    assert out[0].calibration.fits["gyro"].w0_source == "pair_midpoints"
    assert np.isnan(out[0].compensation.query("method == 'uncompensated'")["err_min"]).all()


def test_solve_lstsq_stack_equals_one_problem_at_a_time():
    rng = np.random.default_rng(5)
    X = rng.normal(size=(4, 30, 4)) * np.array([1e-3, 1.0, 1e3, 1.0])
    X[2, :, 3] = 2 * X[2, :, 0]  # one rank-deficient problem
    Y = rng.normal(size=(4, 30, 3))
    st = solve_lstsq_stack(X, Y)
    for r in range(4):
        one = solve_lstsq(X[r], Y[r])
        _assert_same(
            one,
            replace(
                one,
                coef=st.coef[r],
                cov_unscaled=st.cov_unscaled[r],
                sigma2=st.sigma2[r],
                stderr=st.stderr[r],
                residuals=st.residuals[r],
                dof=int(st.dof[r]),
                condition_number=float(st.condition_number[r]),
                rank=int(st.rank[r]),
            ),
        )
    assert st.rank.tolist() == [4, 4, 3, 4]
    # a shared design (2-D X) with a stack of right-hand sides, factorised once
    shared = solve_lstsq_stack(X[0], Y)
    for r in range(4):
        np.testing.assert_array_equal(shared.coef[r], solve_lstsq(X[0], Y[r]).coef)


def test_calibrate_sessions_equals_calibrate_session_with_a_damaged_session(tmp_path):
    from flows.fleet_sim import simulate_fleet
    from flows.unit_pipeline import calibrate_session, calibrate_sessions
    from schemas.dataset import find_sessions

    simulate_fleet(tmp_path / "data", lots=1, units=1, reps=4, seed=5, sample_rate_hz=10.0, bad_sessions=1)
    refs, _ = find_sessions(tmp_path / "data")
    refs = sorted(refs, key=lambda r: r.key.rep)
    together = calibrate_sessions(refs)
    alone = [calibrate_session(r) for r in refs]
    assert sum(o.status == "failed" for o in together) == 1
    for t, a in zip(together, alone):
        assert (t.key, t.status, t.code, t.message, t.warnings, t.fingerprint) == (
            a.key,
            a.status,
            a.code,
            a.message,
            a.warnings,
            a.fingerprint,
        )
        if a.calibration is not None:
            _assert_same(t.calibration, a.calibration)
            assert pickle.dumps(t.residuals) == pickle.dumps(a.residuals)
            assert pickle.dumps(t.compensation) == pickle.dumps(a.compensation)


def test_shared_layout_columns_are_read_only():
    out = calibrate_repetitions(unit_step_means(n=2, seed=13))
    step = out[0].residual_table.columns["step"]
    assert step is out[1].residual_table.columns["step"]  # one array for the group
    with pytest.raises(ValueError):
        step[0] = -1
