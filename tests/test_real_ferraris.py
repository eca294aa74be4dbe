"""Ferraris calibration on imucal's real example session, against imucal itself.

imucal is a test-only dependency (``pip install imucal`` into .venv); the comparison is
skipped with a reason when it is not installed. The recording lives in ../shared beside the
repository; every test here is skipped when it is absent.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from calib_core.effects import MotionContext, get_effect
from calib_core.errors import DesignError
from calib_core.models.ferraris import FERRARIS_SECTIONS, ferraris_calibration
from schemas.calibration_file import load_calibration, save_calibration
from schemas.importers import IMUCAL_G, read_imucal_csv, read_section_list

REAL = Path(__file__).parents[2] / "shared" / "data" / "real" / "imucal"
CSV = REAL / "example_ferraris_session.csv"
SECTIONS = REAL / "example_ferraris_session_list.json"
RATE = 102.4

pytestmark = pytest.mark.skipif(not CSV.exists(), reason=f"real recording absent: {CSV}")


@pytest.fixture(scope="module")
def ours():
    rec = read_imucal_csv(CSV)
    fit = ferraris_calibration(
        rec.gyro,
        rec.accel,
        read_section_list(SECTIONS),
        RATE,
        gyro_unit=rec.gyro_unit,
        accel_unit=rec.accel_unit,
        g_local=rec.g_local,
    )
    return rec, fit


@pytest.fixture(scope="module")
def imucal_result():
    imucal = pytest.importorskip(
        "imucal",
        reason="imucal not installed: `.venv/bin/pip install imucal` (test-only "
        "dependency) to compare with the reference implementation",
    )
    df = pd.read_csv(CSV)
    section_list = pd.DataFrame(json.loads(SECTIONS.read_text())).T
    regions = imucal.ferraris_regions_from_section_list(df, section_list)
    info = imucal.FerrarisCalibration().compute(regions, RATE, "m/s^2", "deg/s")
    acc, gyr = info.calibrate(
        df[["acc_x", "acc_y", "acc_z"]].to_numpy(),
        df[["gyr_x", "gyr_y", "gyr_z"]].to_numpy(),
        "m/s^2",
        "deg/s",
    )
    return info, acc, gyr


def test_importer_reads_the_imucal_session(ours):
    rec, _ = ours
    # README: 10,377 lines including the header -> 10,376 samples (n_samples 0..10375)
    assert len(rec) == 10376 and rec.gyro_unit == "deg/s" and rec.accel_unit == "g"
    raw = pd.read_csv(CSV)
    np.testing.assert_allclose(rec.accel * IMUCAL_G, raw[["acc_x", "acc_y", "acc_z"]].to_numpy())
    assert rec.t[1] == pytest.approx(1 / RATE)


def test_outputs_equal_imucal_on_the_whole_recording(ours, imucal_result):
    """Tolerance 1e-9 of full scale: both evaluate the same closed-form equations in float64
    (imucal with explicit inverses, we with solves), so only rounding may differ; measured
    differences are ~1e-14 m/s^2 and ~1e-13 deg/s."""
    rec, fit = ours
    _, acc_ref, gyr_ref = imucal_result
    w, f = fit.calibration.apply(rec.gyro, rec.accel)
    np.testing.assert_allclose(f * IMUCAL_G, acc_ref, rtol=0, atol=1e-9 * np.abs(acc_ref).max())
    np.testing.assert_allclose(w, gyr_ref, rtol=0, atol=1e-9 * np.abs(gyr_ref).max())


def test_matrices_equal_imucal(ours, imucal_result):
    _, fit = ours
    info, _, _ = imucal_result
    cal = fit.calibration
    acc_mat = np.linalg.inv(info.R_a) @ np.linalg.inv(info.K_a)  # imucal's raw -> m/s^2
    gyr_mat = np.linalg.inv(info.R_g) @ np.linalg.inv(info.K_g)
    np.testing.assert_allclose(cal.K_a, acc_mat, rtol=1e-10)
    np.testing.assert_allclose(cal.f0 * IMUCAL_G, -acc_mat @ info.b_a, rtol=1e-10)
    np.testing.assert_allclose(cal.K_g, gyr_mat, rtol=1e-10)
    np.testing.assert_allclose(cal.w0, -gyr_mat @ info.b_g, rtol=1e-10)
    # imucal's K_ga (deg/s per m/s^2, before the gyro matrix) -> catalogue term, deg/s per g
    # per gyro (along each gyro's own sensing direction, the rows of A_g)
    (term,) = cal.terms
    assert term.name == "gyro_g_sensitivity"
    A_g = cal.geometry.gyro_axes
    np.testing.assert_allclose(term.params.reshape(3, 3), A_g @ gyr_mat @ info.K_ga * IMUCAL_G, rtol=1e-10)
    # applied, it is imucal's body-frame rate error K_g K_ga f
    f = np.array([[0.3, -0.5, 0.8]])
    np.testing.assert_allclose(
        get_effect("gyro_g_sensitivity").error(
            MotionContext.from_refs(np.zeros((1, 3)), f), term.params, cal.geometry
        )[0, :3],
        gyr_mat @ info.K_ga @ f[0] * IMUCAL_G,
        rtol=1e-9,
    )


def test_calibration_file_round_trip_gives_deg_s_and_g(ours, tmp_path):
    rec, fit = ours
    path = save_calibration(fit.calibration, tmp_path / "ferraris.json")
    cal = load_calibration(path)
    assert cal.kind == "ferraris" and cal.gyro_unit == "deg/s" and cal.accel_unit == "g"
    assert cal.g_local == IMUCAL_G
    sec = read_section_list(SECTIONS)
    # independent physical checks: the +/- poses differ by exactly 2 g on their axis (the
    # equations force K_a U_d = 2 I); each pose reads +/-1 g within 1 mg (the bias uses only
    # the diagonal of the pose sums, Ferraris eq. 20, so this is not exact: 0.06 mg measured)
    means = {}
    for name in ("x_p", "x_a", "y_p", "y_a", "z_p", "z_a"):
        a, b = sec[name]
        w, f = cal.apply(rec.gyro[a:b], rec.accel[a:b])
        means[name] = f.mean(axis=0)
        sign = 1 if name.endswith("_p") else -1
        assert means[name]["xyz".index(name[0])] == pytest.approx(sign, abs=1e-3)
        assert np.linalg.norm(means[name]) == pytest.approx(1.0, abs=1e-3)
        assert np.abs(w.mean(axis=0)).max() < 0.05  # deg/s: at rest (earth rate 0.004 deg/s)
    for i, ax in enumerate("xyz"):
        np.testing.assert_allclose(means[f"{ax}_p"] - means[f"{ax}_a"], 2 * np.eye(3)[i], atol=1e-9)
    # ... and every turn integrates to -360 deg about its own axis, ~0 about the others
    for name in ("x_rot", "y_rot", "z_rot"):
        a, b = sec[name]
        w, _ = cal.apply(rec.gyro[a:b], rec.accel[a:b])
        ang = w.sum(axis=0) / RATE
        i = "xyz".index(name[0])
        assert ang[i] == pytest.approx(-360.0, abs=1e-6)
        assert np.abs(np.delete(ang, i)).max() < 1e-6


def test_missing_section_is_a_design_error(ours):
    rec, _ = ours
    sec = read_section_list(SECTIONS)
    del sec["y_rot"]
    with pytest.raises(DesignError) as err:
        ferraris_calibration(rec.gyro, rec.accel, sec, RATE)
    assert err.value.undetermined == ("y_rot",)
    assert set(FERRARIS_SECTIONS) - set(sec) == {"y_rot"}


def test_ferraris_recovers_truth_on_a_synthetic_session():
    """Independent of imucal: a synthetic session from known matrices; the rotation integral
    is exact for the constant-rate turns simulated, so the truth is recovered to rounding."""
    rng = np.random.default_rng(11)
    K_a = np.eye(3) * 1e-3 + rng.normal(0, 2e-5, (3, 3))  # g per count
    f0 = rng.normal(0, 0.02, 3)
    K_g = np.eye(3) * 0.07 + rng.normal(0, 1e-3, (3, 3))  # deg/s per count
    w0 = rng.normal(0, 1, 3)
    S = rng.normal(0, 0.05, (3, 3))  # deg/s per g, true g-sensitivity
    rate, n_static, n_rot = 100.0, 200, 400
    G_parts, A_parts, sections, pos = [], [], {}, 0

    def emit(name, w, f):
        nonlocal pos
        sensed_w = w + f @ S.T
        G_parts.append(np.linalg.solve(K_g, (sensed_w - w0).T).T)
        A_parts.append(np.linalg.solve(K_a, (f - f0).T).T)
        sections[name] = (pos, pos + len(w))
        pos += len(w)

    for i, ax in enumerate("xyz"):
        for sign, suffix in ((1, "p"), (-1, "a")):
            f = np.zeros((n_static, 3))
            f[:, i] = sign
            emit(f"{ax}_{suffix}", np.zeros((n_static, 3)), f)
    for i, ax in enumerate("xyz"):
        # turn of -360 deg about the up axis i: gravity stays along i, rate constant
        w = np.zeros((n_rot, 3))
        w[:, i] = -360.0 / (n_rot / rate)
        f = np.zeros((n_rot, 3))
        f[:, i] = 1
        emit(f"{ax}_rot", w, f)
    fit = ferraris_calibration(np.vstack(G_parts), np.vstack(A_parts), sections, rate)
    cal = fit.calibration
    np.testing.assert_allclose(cal.K_a, K_a, rtol=1e-9)
    np.testing.assert_allclose(cal.f0, f0, atol=1e-12)
    np.testing.assert_allclose(cal.K_g, K_g, rtol=1e-9)
    np.testing.assert_allclose(cal.w0, w0, atol=1e-9)
    # the body-frame g-sensitivity S, per gyro along its own sensing direction: A_g S
    np.testing.assert_allclose(cal.terms[0].params.reshape(3, 3), cal.geometry.gyro_axes @ S, atol=1e-9)


def test_turntable_style_fit_of_the_six_poses_agrees(ours):
    """Where a turntable-style fit applies: xu2016's multiposition fit (F = K_a A + f0, least
    squares) on the six static poses with their nominal +/-1 g references. It must agree with
    the Ferraris matrices within its own standard errors (3 sigma); f0 differs because
    Ferraris uses only the diagonal of the pose sums (measured 0.6-1.9 sigma, 0.4-1.4 mg)."""
    from calib_core.models.ferraris import section_pose_means
    from calib_core.models.xu2016 import fit_accel_multiposition
    from calib_core.steps import SessionKey, StepMeans

    rec, fit = ours
    pm = section_pose_means(rec.t, rec.gyro, rec.accel, read_section_list(SECTIONS))
    assert list(pm["pose"]) == ["x_p", "x_a", "y_p", "y_a", "z_p", "z_a"]
    n = len(pm)
    f_ref = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    sm = StepMeans(
        key=SessionKey("imucal", "example", 1),
        step=np.arange(n),
        test=np.array(["multiposition"] * n),
        up_axis=np.array(["+x", "-x", "+y", "-y", "+z", "-z"]),
        rate_dps=np.zeros(n),
        angle_deg=np.full(n, np.nan),
        w_ref=np.zeros((n, 3)),
        f_ref=f_ref,
        gyro=pm[["gx", "gy", "gz"]].to_numpy(),
        accel=pm[["ax", "ay", "az"]].to_numpy(),
        gyro_std=pm[["gx_std", "gy_std", "gz_std"]].to_numpy(),
        accel_std=pm[["ax_std", "ay_std", "az_std"]].to_numpy(),
        count=pm["count"].to_numpy(),
        t_mid=pm["t_mid"].to_numpy(),
        temp_c=np.full(n, np.nan),
        gyro_unit="deg/s",
        accel_unit="g",
        g_local=IMUCAL_G,
    )
    xu = fit_accel_multiposition(sm)
    cal = fit.calibration
    assert (np.abs(xu.K - cal.K_a) <= 3 * xu.K_stderr).all()
    assert (np.abs(xu.f0 - cal.f0) <= 3 * xu.f0_stderr).all()
