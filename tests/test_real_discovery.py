"""Model discovery on the two real recordings (no turntable references), through the effect
catalogue (calib_core.discovery.static), plus controls on data with known truth.

Thresholds come from the numbers measured in docs/real-discovery.md:
- Xsens (field calibration, 38 poses): gyro_g_sensitivity is found with F = 248 on (9, 102)
  dof (p ~ 1e-65) and a held-out gain of 4.1 (leave 4 consecutive poses out): asserted
  p < 1e-20 and gain > 3, far inside both margins yet failing if the effect were weak (a gain
  of 1.5 would already be a useful but much smaller effect). Nothing else is significant (the
  smallest other p is 0.047 against a Bonferroni threshold of 0.0025).
- Ferraris session (6 poses): nothing significant; imucal's own g-sensitivity term is not
  supported by the six poses (p = 0.16, held-out gain 0.92 < 1).
- Negative controls: the Xsens gyro means shuffled among the poses (orientation and time
  destroyed), and simulated sessions (the field calibration replayed as a simulator on the
  real orientations, noise of the real poses) with and without a known g-sensitivity.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from calib_core.calibration import TermValue
from calib_core.discovery.static import StaticPoses, diagnose_static, pose_residuals
from calib_core.effects import get_effect

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
pytestmark = pytest.mark.skipif(
    not (REAL / "imu_tk" / "xsens_acc.txt").exists()
    or not (REAL / "imucal" / "example_ferraris_session.csv").exists(),
    reason=f"real recordings absent under {REAL} (see shared/data/real/README.md)",
)

NOT_ON_STATIC = {"lever_arm", "gyro_scale_nonlinearity", "gyro_scale_asymmetry"}


@pytest.fixture(scope="module")
def xsens():
    from flows.commands.diagnose_real import load_recording

    cal, poses, label = load_recording("xsens", REAL)
    return cal, poses, diagnose_static(cal, poses, label, block_size=4)


@pytest.fixture(scope="module")
def ferraris():
    from flows.commands.diagnose_real import load_recording

    cal, poses, label = load_recording("ferraris", REAL)
    return cal, poses, diagnose_static(cal, poses, label, block_size=1)


def test_xsens_names_gyro_g_sensitivity_with_heldout_gain(xsens):
    _, _, d = xsens
    assert d.n_poses == 38
    assert [(e.name, e.block) for e in d.effects] == [("gyro_g_sensitivity", "gyro")]
    e = d.effects[0]
    assert e.evidence.p_value < 1e-20 and e.evidence.dof1 == 9
    assert e.gain > 3.0
    assert set(e.axes) == {"x", "y", "z"}
    # the rate left at rest falls from 0.09 deg/s to ~1.3x the white noise of a pose mean
    g = d.blocks["gyro"]
    assert g["baseline_rms"] > 0.08 and g["refit_rms_after"] < 0.02
    assert g["rms_over_white_after"] < 1.6


def test_xsens_nothing_else_and_untestable_terms_reported(xsens):
    _, _, d = xsens
    for c in d.candidates:
        if c.name != "gyro_g_sensitivity":
            assert c.evidence.p_value > c.evidence.threshold, c.name
    listed = {nt["name"] for nt in d.not_testable}
    assert NOT_ON_STATIC <= listed
    assert not NOT_ON_STATIC & {e.name for e in d.effects + d.candidates}
    # the magnitude residual (0.11 mg RMS) is not explained by any catalogue term
    assert d.blocks["accel"]["chosen"] == [] and d.blocks["accel"]["baseline_rms"] < 0.2


def test_xsens_estimate_agrees_with_the_independent_static_fit(xsens):
    """calib_core.models.field.imu_tk's own least-squares fit of b + S f on the pose samples (not the
    catalogue) gives the same matrix, per gyro, within the reported standard errors."""
    from calib_core.models.field.imu_tk import fit_static_gyro_g_sensitivity
    from schemas.importers import read_imutk_pair

    cal, poses, d = xsens
    rec = read_imutk_pair(REAL / "imu_tk" / "xsens_acc.txt", REAL / "imu_tk" / "xsens_gyro.txt")
    f_all = rec.accel @ cal.K_a.T + cal.f0
    intervals = list(zip(poses["start"], poses["end"]))
    _, S_raw = fit_static_gyro_g_sensitivity(rec.gyro, f_all, intervals)
    # the catalogue's g-sensitivity is per gyro (its own sensing direction): the body-frame
    # error matrix K_g S_raw seen by the gyros is A_g K_g S_raw (A_g: their directions)
    independent = (cal.geometry.gyro_axes @ cal.K_g @ S_raw).reshape(-1)
    e = d.effects[0]
    est = np.array([e.estimate[n] for n in get_effect("gyro_g_sensitivity").param_names])
    se = np.array([e.stderr[n] for n in get_effect("gyro_g_sensitivity").param_names])
    assert np.max(np.abs(est - independent) / se) < 1.0


def test_xsens_shuffled_gyro_means_show_nothing(xsens):
    """Negative control: the gyro means (with their std) assigned to random other poses keep
    the real noise and the real orientations but break any link between them and time."""
    cal, poses, _ = xsens
    rng = np.random.default_rng(2026)
    found = 0
    for _ in range(20):
        p = poses.copy()
        perm = rng.permutation(len(p))
        for c in ("gx", "gy", "gz", "gx_std", "gy_std", "gz_std"):
            p[c] = poses[c].to_numpy()[perm]
        d = diagnose_static(cal, p, "shuffled")
        found += bool(d.effects)
    assert found <= 1  # alpha = 0.01 per recording: expect 0.2 of 20


def _simulated_poses(cal, poses, rng, theta=None, tau_g=0.01, tau_a=1e-4):
    """A static session made by replaying the calibration as a simulator
    (Calibration.predict_raw) on the real poses' orientations and times, with white noise of
    the real pose means plus pose-to-pose noise tau; optional true g-sensitivity theta."""
    sp = StaticPoses.from_pose_means(poses)
    _, _, ctx = pose_residuals(cal, sp)
    sim = cal if theta is None else replace(cal, terms=(TermValue("gyro_g_sensitivity", theta),))
    n = len(sp)
    sg = np.sqrt((sp.G_std**2) @ (cal.K_g.T**2)) / np.sqrt(sp.count)[:, None]
    sa = np.sqrt((sp.A_std**2) @ (cal.K_a.T**2)) / np.sqrt(sp.count)[:, None]
    w = rng.normal(size=(n, 3)) * np.sqrt(sg**2 + tau_g**2)
    f = ctx.f + rng.normal(size=(n, 3)) * np.sqrt(sa**2 + tau_a**2)
    G, A = sim.predict_raw(w, f, t=sp.t_mid)
    out = poses.sort_values("t_mid").copy()
    out[["gx", "gy", "gz"]] = G
    out[["ax", "ay", "az"]] = A
    return out


def test_simulated_static_sessions_null_and_known_effect(xsens):
    cal, poses, _ = xsens
    rng = np.random.default_rng(11)
    false_alarms = sum(
        bool(diagnose_static(cal, _simulated_poses(cal, poses, rng), "null").effects) for _ in range(25)
    )
    assert false_alarms <= 1
    theta = np.zeros(9)
    theta[[1, 3, 5]] = [0.03, -0.04, 0.02]  # deg/s per g, the size seen on real MEMS units
    names = get_effect("gyro_g_sensitivity").param_names
    est, se, exact = [], [], 0
    for _ in range(25):
        d = diagnose_static(cal, _simulated_poses(cal, poses, rng, theta), "effect")
        exact += [(e.name, e.block) for e in d.effects] == [("gyro_g_sensitivity", "gyro")]
        e = next(e for e in d.effects + d.candidates if e.name == "gyro_g_sensitivity")
        est.append([e.estimate[n] for n in names])
        se.append([e.stderr[n] for n in names])
    est, se = np.array(est), np.array(se)
    assert exact >= 24
    spread = est.std(axis=0, ddof=1)
    # unbiased (mean within 4 standard errors of the mean) and standard errors honest
    assert np.all(np.abs(est.mean(axis=0) - theta) < 4 * spread / np.sqrt(len(est)))
    ratio = np.sqrt((se**2).mean(axis=0)) / spread
    assert np.all((ratio > 0.6) & (ratio < 1.6)), ratio


def test_ferraris_session_shows_nothing_significant(ferraris):
    _, _, d = ferraris
    assert d.n_poses == 6 and d.effects == [] and not d.misfit
    cand = {(c.name, c.block): c for c in d.candidates}
    assert set(cand) == {("bias_time_drift", "gyro")}  # no temperature: time only
    assert cand[("bias_time_drift", "gyro")].evidence.p_value > 0.1
    # six axis-aligned poses fix |f| exactly: the accelerometer cannot be tested here
    assert d.blocks["accel"]["dof_after"] == 0
    reasons = {(nt["name"], nt.get("block")) for nt in d.not_testable}
    assert ("accel_scale_nonlinearity", "accel") in reasons
    assert ("gyro_g_sensitivity", None) in reasons  # part of the Ferraris baseline
    # the rate at rest is at the white noise of a pose mean (0.002 deg/s)
    assert d.blocks["gyro"]["baseline_rms"] < 0.003
    assert d.blocks["gyro"]["chi2_white_p_after"] > 0.01


def test_ferraris_own_g_sensitivity_is_not_supported_by_the_poses(ferraris):
    _, _, d = ferraris
    (chk,) = d.baseline_checks
    assert chk.name == "gyro_g_sensitivity" and chk.evidence.dof1 == 9
    assert chk.evidence.p_value > 0.01 and chk.gain < 1.0


def test_cli_writes_the_json(tmp_path, ferraris):
    from flows.cli import main
    from schemas.calibration_file import save_calibration

    out = tmp_path / "f.json"
    assert main(["diagnose-real", "ferraris", "--data", str(REAL), "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    for k in ("recording", "misfit", "unexplained", "effects", "not_testable"):
        assert k in doc
    assert doc["effects"] == [] and doc["misfit"] is False
    # the generic form: any pose table + calibration file gives the same answer
    cal, poses, d = ferraris
    save_calibration(cal, tmp_path / "cal.json")
    poses.to_csv(tmp_path / "poses.csv", index=False)
    out2 = tmp_path / "p.json"
    assert (
        main(
            [
                "diagnose-real",
                "poses",
                "--poses",
                str(tmp_path / "poses.csv"),
                "--calibration",
                str(tmp_path / "cal.json"),
                "--json",
                str(out2),
            ]
        )
        == 0
    )
    doc2 = json.loads(out2.read_text())
    assert doc2["blocks"]["gyro"]["baseline_rms"] == pytest.approx(d.blocks["gyro"]["baseline_rms"], rel=1e-9)
    assert main(["diagnose-real", "poses"]) == 2
