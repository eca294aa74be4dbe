"""The fit-stage speed work (issue 7) changed how results are computed, not what they are.

Each fast path is checked against an independent computation (per-session pandas DataFrames
built the plain way, fresh selections) or against the truth of a noise-free simulation (the
batched all-determined lever-arm solve). Seeded simulations.
"""

from __future__ import annotations

import pickle
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest

from calib_core.models import xu2016, zhang2017
from calib_core.models.pipeline import (
    RESIDUAL_COLUMNS,
    baseline_residuals,
    calibrate_repetition,
    calibration_from_fits,
)
from calib_core.results import RepetitionCalibration, summarise
from calib_core.sim import accel_unit, protocols, simulator
from calib_core.steps import SessionKey, StepMeans
from calib_core.tables import CodedStrings, ColumnTable
from flows.unit_pipeline import SessionOutcome, aggregate_unit

STEPS = protocols.default_session(verification=True)


def _sessions(n: int = 3, seed: int = 41, steps=STEPS) -> list[StepMeans]:
    rng = np.random.default_rng(seed)
    truth = simulator.typical_truth(rng)
    return [
        simulator.simulate_step_means(truth, steps, rng, key=SessionKey("L9", "U9", r))
        for r in range(1, n + 1)
    ]


# -- tables ---------------------------------------------------------------------------------
def _plain_residuals(sm: StepMeans, fit) -> pd.DataFrame:
    """The per-session residual frame as the pipeline built it before: numpy columns, string
    columns repeated as numpy strings, one pandas DataFrame per session."""
    cal = calibration_from_fits(fit.calibration.fits, sm)
    w, f = cal.apply(sm.gyro, sm.accel)
    n = np.sqrt(np.maximum(sm.count, 1))[:, None]
    sig = np.hstack(
        [np.sqrt((sm.gyro_std**2) @ (cal.K_g.T**2)) / n, np.sqrt((sm.accel_std**2) @ (cal.K_a.T**2)) / n]
    )
    return pd.DataFrame(
        {
            "lot": sm.key.lot,
            "unit": sm.key.unit,
            "rep": sm.key.rep,
            "step": np.repeat(sm.step, 6),
            "test": np.repeat(sm.test, 6),
            "up_axis": np.repeat(sm.up_axis, 6),
            "rate_dps": np.repeat(sm.rate_dps, 6),
            "angle_deg": np.repeat(sm.angle_deg, 6),
            "channel": np.tile(np.array(["gx", "gy", "gz", "ax", "ay", "az"]), len(sm)),
            "reference": np.hstack([sm.w_ref, sm.f_ref]).ravel(),
            "residual": np.hstack([w - sm.w_ref, f - sm.f_ref]).ravel(),
            "sigma": sig.ravel(),
            "model": "baseline",
        },
        columns=RESIDUAL_COLUMNS,
    )


def _plain_compensation(sm: StepMeans, fit) -> pd.DataFrame:
    """Table 3 rows from a loop over methods and axes (the former implementation)."""
    fits = fit.calibration.fits
    st = sm.of_test("verification")
    st = st.select(np.abs(st.rate_dps) > 0)
    outputs = {
        "uncompensated": st.gyro,
        "proposed": fits["gyro"].compensate(st.gyro),
        "traditional": fits["gyro_traditional"].compensate(st.gyro),
    }
    inp = np.array(list("xyz"))[np.argmax(np.abs(st.w_ref), axis=1)]
    rows = []
    for method, out in outputs.items():
        err = out - st.w_ref
        for a in "xyz":
            sel = inp == a
            if sel.any():
                for j, b in enumerate("xyz"):
                    rows.append(
                        {
                            "input_axis": a,
                            "output_axis": b,
                            "method": method,
                            "err_min": float(err[sel, j].min()),
                            "err_max": float(err[sel, j].max()),
                            "unit_of_measure": "deg/s",
                            "source": "verification",
                            "n_steps": int(sel.sum()),
                        }
                    )
    return pd.DataFrame(rows)


def test_session_tables_equal_the_plain_dataframes():
    for sm in _sessions(2):
        fit = calibrate_repetition(sm)
        pd.testing.assert_frame_equal(fit.residuals, _plain_residuals(sm, fit), check_exact=True)
        pd.testing.assert_frame_equal(fit.compensation, _plain_compensation(sm, fit), check_exact=True)
        pd.testing.assert_frame_equal(
            baseline_residuals(sm, calibration_from_fits(fit.calibration.fits, sm)),
            fit.residuals,
            check_exact=True,
        )


def test_unit_frames_equal_concatenated_session_frames():
    """UnitOutcome builds one frame from the sessions' column tables; it must equal what
    concatenating per-session DataFrames (with lot/unit/rep inserted first) gives."""
    sessions = _sessions(3)
    outcomes, res_frames, comp_frames = [], [], []
    for sm in sessions:
        fit = calibrate_repetition(sm)
        outcomes.append(
            SessionOutcome(
                sm.key,
                None,
                "ok",
                None,
                None,
                [],
                "",
                fit.calibration,
                fit.residual_table,
                fit.compensation_table,
                sm,
            )
        )
        res_frames.append(_plain_residuals(sm, fit))
        comp = _plain_compensation(sm, fit)
        for c, v in (("lot", "L9"), ("unit", "U9"), ("rep", sm.key.rep)):
            comp.insert(0, c, v)
        comp_frames.append(comp)
    # a failed session contributes nothing
    outcomes.append(SessionOutcome(SessionKey("L9", "U9", 9), None, "failed", "E_X", "x", [], ""))
    unit = aggregate_unit("L9", "U9", outcomes)
    pd.testing.assert_frame_equal(
        unit.residuals_frame(), pd.concat(res_frames, ignore_index=True), check_exact=True
    )
    pd.testing.assert_frame_equal(
        unit.compensation_frame(), pd.concat(comp_frames, ignore_index=True), check_exact=True
    )
    assert list(unit.compensation_frame().columns[:3]) == ["rep", "unit", "lot"]


def test_column_table_concat_and_frame():
    a = ColumnTable(
        {
            "k": "A",
            "n": 1,
            "s": CodedStrings(np.array(["x", "y"]), np.array([1, 0, 1])),
            "v": np.array([1.0, 2.0, 3.0]),
            "m": "base",
        },
        3,
    )
    b = ColumnTable(
        {
            "k": "A",
            "n": 2,
            "s": CodedStrings(np.array(["z", "x"]), np.array([0, 1])),
            "v": np.array([4.0, 5.0]),
            "m": "ext",
        },
        2,
    )
    c = ColumnTable.concat([a, b])
    assert c.columns["k"] == "A"  # the same scalar everywhere stays a scalar
    assert c.column("n").tolist() == [1, 1, 1, 2, 2]
    assert c.column("s").tolist() == ["y", "x", "y", "z", "x"]
    assert c.column("m").tolist() == ["base"] * 3 + ["ext"] * 2
    expected = pd.concat(
        [
            pd.DataFrame(
                {"k": "A", "n": 1, "s": np.array(["y", "x", "y"]), "v": [1.0, 2.0, 3.0], "m": "base"}
            ),
            pd.DataFrame({"k": "A", "n": 2, "s": np.array(["z", "x"]), "v": [4.0, 5.0], "m": "ext"}),
        ],
        ignore_index=True,
    )
    pd.testing.assert_frame_equal(c.to_frame(), expected, check_exact=True)
    assert list(c.with_leading("first", 7).columns)[0] == "first"
    with pytest.raises(ValueError):
        ColumnTable.concat([a, ColumnTable({"v": np.zeros(1)}, 1)])
    with pytest.raises(ValueError):
        ColumnTable({"v": np.zeros(2)}, 3)
    empty = ColumnTable({"x": np.empty(0), "y": np.empty(0)}, 0).to_frame()
    pd.testing.assert_frame_equal(empty, pd.DataFrame(columns=["x", "y"]))


# -- numerics -----------------------------------------------------------------------------------
def test_multirate_pairs_are_opposite_rates_about_one_axis():
    sm = _sessions(1)[0]
    dG, dW, pairs = xu2016.multirate_pairs(sm)
    p, m = pairs[:, 0], pairs[:, 1]
    assert (sm.rate_dps[p] > 0).all() and np.allclose(sm.rate_dps[p], -sm.rate_dps[m])
    np.testing.assert_allclose(sm.w_ref[p], -sm.w_ref[m])
    # every multirate step with a rate is in exactly one pair (the protocol pairs them all)
    rotating = np.flatnonzero((sm.test == "multirate") & (sm.rate_dps != 0))
    assert sorted(pairs.ravel().tolist()) == rotating.tolist()
    np.testing.assert_array_equal(dW, 2 * sm.w_ref[p])
    np.testing.assert_array_equal(dG, sm.gyro[p] - sm.gyro[m])


def test_lever_arm_all_determined_recovers_the_truth_when_noise_free():
    # tilted dynamic steps: every component determined, the block-diagonal batched solve
    lever = np.array([[5, -3, 2], [-4, 6, 1], [2, 3, -7.0]])
    truth = accel_unit.AccelUnitTruth(
        scale=np.array([0.5, 0.51, 0.49]),
        bias=np.array([0.01, -0.02, 0.03]),
        C=zhang2017.C_from_angles(np.array([[0.5, 89.5, 90.2], [90.3, 0.7, 89.6], [89.8, 90.4, 0.6]])),
        lever_arm_mm=lever,
    ).to_mimu_truth(accel_noise_g=0.0, accel_bias_instability_g=0.0)
    sm = simulator.simulate_step_means(truth, protocols.default_session(), np.random.default_rng(3))
    static = zhang2017.fit_accel_static(sm)
    for projection in zhang2017.PROJECTIONS:
        fit = zhang2017.fit_lever_arm(sm, static, projection=projection)  # rates: w_ref
        assert fit.undetermined == () and fit.dof == 3 * fit.n_steps - 9
        # the truth is the paper's sensitive-axis model; the body-axis model differs from it
        # by misalignment x lever term (~1 % of r here)
        tol = 1e-6 if projection == "sensitive_axis" else 0.3
        np.testing.assert_allclose(fit.lever_arm_mm, lever, atol=tol)
        assert np.all(fit.stderr > 0) and fit.condition_number < 10
        inputs = zhang2017.lever_arm_inputs(sm, static)
        np.testing.assert_array_equal(
            zhang2017.lever_arm_estimate(inputs, projection=projection), fit.lever_arm_mm
        )


def test_lever_arm_estimate_with_undetermined_components():
    rng = np.random.default_rng(4)
    steps = protocols.to_frame(
        protocols.xu2016_multirate()
        + protocols.xu2016_multiposition()
        + protocols.dynamic_steps(tilted=False)
    )
    sm = simulator.simulate_step_means(simulator.typical_truth(rng), steps, rng)
    static = zhang2017.fit_accel_static(sm)
    full = zhang2017.fit_lever_arm(sm, static, projection="body_axis")
    assert full.undetermined  # untilted steps: off-diagonal components unobservable
    est = zhang2017.lever_arm_estimate(zhang2017.lever_arm_inputs(sm, static), projection="body_axis")
    np.testing.assert_array_equal(est, full.lever_arm_mm)  # NaN where undetermined


# -- aggregate -----------------------------------------------------------------------------------
def test_summarise_over_repetitions():
    reps = [calibrate_repetition(sm).calibration for sm in _sessions(3)]
    out = summarise(reps)
    assert len(out) == len(reps[0].parameters()) and all(x.n_reps == 3 for x in out)
    # independent: the statistics of one parameter over the repetitions
    k11 = [p.value for r in reps for p in r.parameters() if p.name == "k_g11"]
    s = next(x for x in out if x.name == "k_g11")
    assert s.values == tuple(k11)
    assert s.mean == pytest.approx(np.mean(k11), rel=1e-15)
    assert s.std == pytest.approx(np.std(k11, ddof=1), rel=1e-12)
    # a repetition without the lever-arm model: counts per parameter
    short = replace(reps[0], fits={k: v for k, v in reps[0].fits.items() if k != "lever_arm"})
    mixed = summarise([short] + reps[1:])
    by_name = {(x.model, x.name): x for x in mixed}
    assert by_name[("gyro", "k_g11")].n_reps == 3
    assert by_name[("lever_arm", "r1x")].n_reps == 2


def test_parameters_cache_follows_the_fits():
    rep = calibrate_repetition(_sessions(1)[0]).calibration
    first = rep.parameters()
    assert rep.parameters() == first and rep.parameters() is not first
    del rep.fits["lever_arm"]
    assert len(rep.parameters()) == len(first) - 9
    assert "_parameters" not in pickle.loads(pickle.dumps(rep)).__dict__
    assert isinstance(pickle.loads(pickle.dumps(rep)), RepetitionCalibration)


def test_of_test_subsets_are_kept_and_equal_a_fresh_selection():
    sm = _sessions(1)[0]
    dyn = sm.of_test("dynamic")
    assert sm.of_test("dynamic") is dyn
    mask = sm.test == "dynamic"
    for name in ("step", "test", "w_ref", "gyro", "accel_std", "count", "temp_c"):
        np.testing.assert_array_equal(getattr(dyn, name), getattr(sm, name)[mask])
    assert (dyn.key, dyn.gyro_unit, dyn.g_local) == (sm.key, sm.gyro_unit, sm.g_local)
    again = pickle.loads(pickle.dumps(sm))
    assert "_subsets" not in again.__dict__
    np.testing.assert_array_equal(again.of_test("dynamic").gyro, dyn.gyro)
    assert "_subsets" not in replace(sm).__dict__


def test_cpu_by_stage_adds_up_and_changes_nothing():
    import time

    from calib_core.models.pipeline import STAGES

    sm = _sessions(1)[0]
    plain = calibrate_repetition(sm)
    cpu: dict = {}
    t0 = time.process_time()
    timed = calibrate_repetition(sm, cpu_by_stage=cpu)
    total = time.process_time() - t0
    assert set(cpu) == set(STAGES) and all(v >= 0 for v in cpu.values())
    assert sum(cpu.values()) <= total + 1e-6
    assert timed.calibration.parameters() == plain.calibration.parameters()
    pd.testing.assert_frame_equal(timed.residuals, plain.residuals, check_exact=True)
    calibrate_repetition(sm, cpu_by_stage=cpu)  # a second session adds to the same dict
    assert sum(cpu.values()) > 0
