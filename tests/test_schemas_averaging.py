"""Step averaging: equals a naive per-step pandas computation; settling, saturated, too-short
and empty steps; unit conversion (rad/s, m/s^2) and raw units (LSB, V)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from calib_core.sim import protocols
from calib_core.sim import simulator as sim
from calib_core.steps import SessionKey
from schemas import errors as E
from schemas.averaging import read_step_means, step_means_from_tables
from schemas.dataset import SessionRef
from schemas.writer import write_session

RATE = 50.0
KEY = SessionKey("L1", "U001", 1)


def protocol(duration_s=1.0, settle_s=0.2):
    return protocols.default_session(duration_s=duration_s, settle_s=settle_s)


def simulate(truth, steps, seed=7, rate=RATE):
    rng = np.random.default_rng(seed)
    return sim.simulate_session(truth, steps, rng, rate), sim.session_metadata(truth, rate)


def write(root, key, steps, samples, md, **kw) -> SessionRef:
    return SessionRef(key, write_session(root, key, steps, samples, md, **kw))


def naive_means(steps: pd.DataFrame, samples: pd.DataFrame) -> pd.DataFrame:
    """The textbook computation, per step with pandas (independent of schemas.averaging)."""
    rows = []
    settle = dict(zip(steps["step"], steps["settle_s"]))
    for step_id, g in samples[samples["step"] != -1].groupby("step", sort=False):
        kept = g[g["t"] - g["t"].iloc[0] >= settle[step_id] - 1e-6]
        row = {"step": step_id, "count": len(kept), "t_mid": (kept["t"].iloc[0] + kept["t"].iloc[-1]) / 2}
        for c in ("gx", "gy", "gz", "ax", "ay", "az"):
            x = kept[c].astype(np.float64)
            row[c] = x.mean()
            row[c + "_std"] = x.std(ddof=1)
        if "temp_c" in kept:
            row["temp_c"] = kept["temp_c"].astype(np.float64).mean()
        rows.append(row)
    return pd.DataFrame(rows).set_index("step")


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    rng = np.random.default_rng(3)
    truth = replace(sim.typical_truth(rng), temperature=sim.TemperatureProfile())
    steps = protocol()
    samples, md = simulate(truth, steps)
    root = tmp_path_factory.mktemp("avg")
    return truth, steps, samples, md, write(root, KEY, steps, samples, md)


def test_averaging_equals_naive_pandas(session):
    truth, steps, samples, md, ref = session
    sm, warnings = read_step_means(ref)
    assert warnings == []
    naive = naive_means(steps, samples).loc[sm.step]
    np.testing.assert_array_equal(sm.count, naive["count"].to_numpy())
    for j, c in enumerate(("gx", "gy", "gz")):
        np.testing.assert_allclose(sm.gyro[:, j], naive[c], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(sm.gyro_std[:, j], naive[c + "_std"], rtol=1e-9)
    for j, c in enumerate(("ax", "ay", "az")):
        np.testing.assert_allclose(sm.accel[:, j], naive[c], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(sm.accel_std[:, j], naive[c + "_std"], rtol=1e-9)
    np.testing.assert_allclose(sm.t_mid, naive["t_mid"], rtol=1e-12)
    np.testing.assert_allclose(sm.temp_c, naive["temp_c"], rtol=1e-9)
    # references come from steps.parquet unchanged
    np.testing.assert_array_equal(sm.w_ref, steps[["w_ref_x", "w_ref_y", "w_ref_z"]].to_numpy())
    assert list(sm.test) == list(steps["test"])


def test_settling_drops_first_settle_s(session):
    _, steps, _, _, ref = session
    sm, _ = read_step_means(ref)
    # 1.0 s at 50 Hz = 50 samples per step, minus 0.2 s * 50 Hz = 10 settling samples
    assert (sm.count == 40).all()


def test_means_agree_with_truth(session):
    """Independent of any averaging code: the mean raw output of a step is K^-1 (ref - bias)
    within noise (white noise / sqrt(n) plus the per-step bias instability)."""
    truth, steps, _, _, ref = session
    sm, _ = read_step_means(ref)
    G = np.linalg.solve(truth.K_g, (sm.w_ref - truth.w0).T).T
    A = np.linalg.solve(truth.K_a, (sm.f_ref - truth.f0).T).T
    sd_g = np.hypot(truth.gyro_noise_dps / np.sqrt(40), truth.gyro_bias_instability_dps)
    sd_a = np.hypot(truth.accel_noise_g / np.sqrt(40), truth.accel_bias_instability_g)
    z_g = (sm.gyro - G) / sd_g
    z_a = (sm.accel - A) / sd_a
    assert np.abs(z_g).max() < 5 and np.abs(z_a).max() < 5
    assert 0.8 < z_g.std() < 1.25 and 0.8 < z_a.std() < 1.25


def test_metadata_is_provenance(session):
    *_, md, ref = session
    sm, _ = read_step_means(ref)
    assert sm.metadata == md
    assert sm.sample_rate_hz == RATE and sm.g_local == pytest.approx(9.80665)
    assert sm.gyro_range_dps == tuple(md_val for md_val in (350.0, 350.0, 4000.0))


def test_in_memory_tables_equal_files(session):
    _, steps, samples, md, ref = session
    from_files, _ = read_step_means(ref)
    table = pa.Table.from_pandas(samples, preserve_index=False)
    in_memory, warnings = step_means_from_tables(str(KEY), steps, table, md)
    assert warnings == [] and in_memory.key == KEY
    np.testing.assert_array_equal(in_memory.gyro, from_files.gyro)
    np.testing.assert_array_equal(in_memory.accel_std, from_files.accel_std)


def test_rad_s_and_m_s2_average_like_deg_s_and_g(tmp_path):
    rng = np.random.default_rng(11)
    truth = replace(sim.typical_truth(rng), g_local=9.7940)
    steps = protocol()
    samples, md = simulate(truth, steps)
    base, _ = read_step_means(write(tmp_path, KEY, steps, samples, md))
    key2 = SessionKey("L1", "U001", 2)
    si, w = read_step_means(write(tmp_path, key2, steps, samples, md, gyro_unit="rad/s", accel_unit="m/s^2"))
    assert w == []
    md_si = pq.read_schema(tmp_path / "lot=L1/unit=U001/rep=2/samples.parquet").metadata
    assert md_si[b"gyro_unit"] == b"rad/s" and md_si[b"accel_unit"] == b"m/s^2"
    assert si.gyro_unit == "deg/s" and si.accel_unit == "g"
    # float32 storage: relative rounding 6e-8 per sample
    np.testing.assert_allclose(si.gyro, base.gyro, rtol=2e-7, atol=1e-6)
    np.testing.assert_allclose(si.accel, base.accel, rtol=2e-7, atol=1e-7)
    np.testing.assert_allclose(si.gyro_std, base.gyro_std, rtol=2e-3)
    np.testing.assert_allclose(si.accel_std, base.accel_std, rtol=2e-3)
    # the m/s^2 file really holds m/s^2 (g_local from metadata, not 9.80665)
    raw = pq.read_table(tmp_path / "lot=L1/unit=U001/rep=2/samples.parquet")
    np.testing.assert_allclose(raw["az"].to_numpy(), samples["az"].to_numpy() * 9.7940, rtol=1e-6)


def test_lsb_and_volts_stay_raw(tmp_path):
    """131 LSB per deg/s gyro, 0.5 g/V accelerometer: the averages are in LSB and V, and equal
    K^-1 (ref - bias) in those units."""
    rng = np.random.default_rng(5)
    base = sim.typical_truth(rng)
    truth = replace(base, K_g=base.K_g / 131.0, K_a=base.K_a * 0.5, gyro_unit="LSB", accel_unit="V")
    steps = protocol()
    samples, md = simulate(truth, steps)
    sm, warnings = read_step_means(write(tmp_path, KEY, steps, samples, md))
    assert warnings == []
    assert sm.gyro_unit == "LSB" and sm.accel_unit == "V"
    G = np.linalg.solve(truth.K_g, (sm.w_ref - truth.w0).T).T
    A = np.linalg.solve(truth.K_a, (sm.f_ref - truth.f0).T).T
    assert np.abs(sm.gyro).max() > 3000 * 131 * 0.9  # counts, not deg/s
    sd_g = 131.0 * np.hypot(truth.gyro_noise_dps / np.sqrt(40), truth.gyro_bias_instability_dps)
    sd_a = 2.0 * np.hypot(truth.accel_noise_g / np.sqrt(40), truth.accel_bias_instability_g)
    assert np.abs((sm.gyro - G) / sd_g).max() < 5
    assert np.abs((sm.accel - A) / sd_a).max() < 5


def _saturating_truth(seed, **kw):
    rng = np.random.default_rng(seed)
    # x and y gyros rated +/-250 deg/s: the +/-300 deg/s multirate steps about x and y clip
    return replace(sim.typical_truth(rng), gyro_range_dps=(250.0, 250.0, 4000.0), **kw)


def _expected_saturated(steps):
    m = (
        (steps["test"] == "multirate")
        & (steps["rate_dps"].abs() == 300)
        & steps["up_axis"].isin(["+x", "+y"])
    )
    return set(steps.loc[m, "step"].astype(int))


def test_saturated_steps_are_left_out_and_named(tmp_path):
    truth = _saturating_truth(21)
    steps = protocol()
    samples, md = simulate(truth, steps)
    sm, warnings = read_step_means(write(tmp_path, KEY, steps, samples, md))
    expected = _expected_saturated(steps)
    assert len(expected) == 4
    assert {w.step for w in warnings} == expected
    assert all(w.code == E.W_SATURATED for w in warnings)
    assert all(str(KEY) in w.message and "left out" in w.message for w in warnings)
    assert {w.column for w in warnings} <= {"gx", "gy"}
    assert not expected & set(sm.step.tolist())
    assert len(sm) == len(steps) - 4
    for w in warnings:
        print(w)


def test_saturation_in_raw_units_without_declared_full_scale(tmp_path):
    """LSB data: no full scale in physical units, clipping found as a repeated extreme."""
    base = _saturating_truth(22)
    truth = replace(base, K_g=base.K_g / 131.0, gyro_unit="LSB", gyro_quantum=1.0)
    steps = protocol()
    samples, md = simulate(truth, steps)
    sm, warnings = read_step_means(write(tmp_path, KEY, steps, samples, md))
    assert {w.step for w in warnings} == _expected_saturated(steps)
    assert all("clipped" in w.message for w in warnings)


def test_saturation_in_raw_units_with_declared_full_scale(tmp_path):
    base = _saturating_truth(23)
    truth = replace(base, K_g=base.K_g / 131.0, gyro_unit="LSB")
    steps = protocol()
    samples, md = simulate(truth, steps)
    lo, hi = truth.full_scale_raw()[0]  # raw clips at lo/hi; declare the symmetric bound
    fs = np.minimum(np.abs(lo), np.abs(hi))
    md["gyro_full_scale_raw"] = ",".join(f"{v:.6f}" for v in fs * (1 - 1e-6))
    sm, warnings = read_step_means(write(tmp_path, KEY, steps, samples, md))
    assert {w.step for w in warnings} == _expected_saturated(steps)
    assert all("declared full scale" in w.message for w in warnings)
    print(warnings[0])


@pytest.mark.parametrize("seed", [24, 25, 26])
def test_quantised_raw_data_without_clipping_gives_no_saturation(seed):
    """A +/-2000 deg/s gyro (16.4 LSB per deg/s, noise 0.8 LSB) and a 2048 LSB/g
    accelerometer repeat their extreme codes, but as a thinning noise tail, not a pile-up:
    nothing is left out."""
    base = sim.typical_truth(np.random.default_rng(seed))
    truth = replace(
        base,
        K_g=base.K_g / 16.4,
        gyro_unit="LSB",
        gyro_quantum=1.0,
        K_a=base.K_a / 2048.0,
        accel_unit="LSB",
        accel_quantum=1.0,
    )
    steps = protocol()
    samples, md = simulate(truth, steps, seed=seed)
    _, warnings = step_means_from_tables(KEY, steps, samples, md)
    assert warnings == []


def test_too_short_and_empty_steps(tmp_path):
    rng = np.random.default_rng(8)
    truth = sim.typical_truth(rng)
    steps = protocol()
    # 50 samples at t0 + 0.00 .. 0.98 s: only those at 0.96 and 0.98 s are kept
    steps.loc[steps["step"] == 4, "settle_s"] = 0.95
    samples, md = simulate(truth, steps)
    # a step defined in steps.parquet but never recorded
    extra = steps.iloc[[0]].copy()
    extra["step"] = np.int32(500)
    steps_plus = pd.concat([steps, extra], ignore_index=True)
    sm, warnings = read_step_means(write(tmp_path, KEY, steps_plus, samples, md))
    by_code = {w.code: w for w in warnings}
    assert set(by_code) == {E.W_TOO_SHORT, E.W_EMPTY_STEP}
    assert by_code[E.W_TOO_SHORT].step == 4 and "2 sample(s) after settling" in by_code[E.W_TOO_SHORT].message
    assert by_code[E.W_EMPTY_STEP].step == 500
    assert 4 not in sm.step and 500 not in sm.step and len(sm) == len(steps) - 1
    for w in warnings:
        print(w)


def test_min_samples_threshold(session):
    *_, ref = session
    sm, warnings = read_step_means(ref, min_samples=40)
    assert warnings == [] and len(sm) == 118
    with pytest.raises(E.SessionError) as info:
        read_step_means(ref, min_samples=41)
    assert info.value.code == E.E_EMPTY_SESSION


def test_averaging_is_vectorised_fast(tmp_path):
    """One 118-step session at 200 Hz (3 s steps, 71k samples) averages well under a second."""
    import time

    rng = np.random.default_rng(9)
    truth = sim.typical_truth(rng)
    steps = protocols.default_session()
    samples, md = simulate(truth, steps, rate=200.0)
    ref = write(tmp_path, KEY, steps, samples, md)
    read_step_means(ref)
    start = time.perf_counter()
    read_step_means(ref)
    assert time.perf_counter() - start < 1.0
