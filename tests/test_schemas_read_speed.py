"""The speed paths of reading and averaging (docs/benchmarks.md) give the answers of an
independent computation: per-segment sums (several runs per step), the (6, n) channel array
and its fallback when gyro / accel are replaced, the cached step columns, the saturation
pre-check (the exact rules decide whenever it lets them), the one-pass finiteness check, and
precision with large offsets."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pandas as pd
import pyarrow as pa
import pytest

from calib_core.sim import protocols
from calib_core.sim import simulator as sim
from calib_core.steps import SessionKey
from schemas import averaging, segments
from schemas.averaging import average_session, read_step_means
from schemas.dataset import SessionRef
from schemas.errors import E_NONFINITE_VALUE, SessionError
from schemas.reader import read_session, session_from_tables
from schemas.writer import write_session

RATE = 20.0
KEY = SessionKey("L1", "U1", 1)
CHANNELS = ("gx", "gy", "gz", "ax", "ay", "az")


def _simulate(seed: int, settle_s: float = 0.2, temperature: bool = False):
    rng = np.random.default_rng(seed)
    truth = sim.typical_truth(rng)
    if temperature:
        truth = dataclasses.replace(truth, temperature=sim.TemperatureProfile())
    steps = protocols.default_session(duration_s=1.0, settle_s=settle_s)
    samples = sim.simulate_session(truth, steps, rng, RATE)
    return steps, samples, sim.session_metadata(truth, RATE)


def _naive(steps: pd.DataFrame, samples: pd.DataFrame) -> pd.DataFrame:
    """Per step with pandas and math.fsum: first kept sample time from the step's first
    sample, mean and two-pass std (ddof=1), count, mid time, mean finite temperature."""
    settle = dict(zip(steps["step"], steps["settle_s"]))
    rows = {}
    for step_id, g in samples[samples["step"] != -1].groupby("step"):
        g = g.sort_values("t")
        kept = g[g["t"] - g["t"].iloc[0] >= settle[step_id] - 1e-6]
        row = {"count": len(kept), "t_mid": (kept["t"].iloc[0] + kept["t"].iloc[-1]) / 2}
        for c in CHANNELS:
            x = kept[c].to_numpy(np.float64)
            m = math.fsum(x) / len(x)
            row[c] = m
            row[c + "_std"] = math.sqrt(math.fsum((x - m) ** 2) / (len(x) - 1))
        if "temp_c" in kept:
            tc = kept["temp_c"].to_numpy(np.float64)
            tc = tc[np.isfinite(tc)]
            row["temp_c"] = math.fsum(tc) / len(tc) if len(tc) else np.nan
        rows[int(step_id)] = row
    return pd.DataFrame.from_dict(rows, orient="index")


def _assert_matches_naive(sm, naive: pd.DataFrame, rtol: float = 1e-12) -> None:
    naive = naive.loc[sm.step]
    np.testing.assert_array_equal(sm.count, naive["count"].to_numpy())
    np.testing.assert_allclose(sm.t_mid, naive["t_mid"], rtol=0, atol=1e-12)
    for j, c in enumerate(CHANNELS):
        mean, std = (sm.gyro, sm.gyro_std) if j < 3 else (sm.accel, sm.accel_std)
        scale = np.abs(naive[c].to_numpy()).max()
        np.testing.assert_allclose(mean[:, j % 3], naive[c], rtol=0, atol=rtol * scale)
        np.testing.assert_allclose(std[:, j % 3], naive[c + "_std"], rtol=1e-9)
    if "temp_c" in naive:
        np.testing.assert_allclose(sm.temp_c, naive["temp_c"], rtol=1e-12)


def test_steps_in_several_runs_average_like_pandas():
    """Steps split into many runs by between-step samples (id -1) inside them: several
    segments per step are added up per step. (Steps interleaved with each other are
    E_STEP_NOT_CONTIGUOUS: tests/test_hardening_fault_injection_corpus.py.)"""
    steps, samples, md = _simulate(31, temperature=True)
    s = samples.copy()
    ids = s["step"].to_numpy().copy()
    a, b, c = (int(x) for x in steps["step"].iloc[:3])
    rows = np.flatnonzero(np.isin(ids, [a, b, c]))
    ids[rows[3::8]] = -1  # between-steps samples inside each of the three steps
    s["step"] = ids
    temp = s["temp_c"].to_numpy().copy()
    temp[::7] = np.nan  # a temperature not recorded for some samples
    s["temp_c"] = temp.astype(np.float32)
    steps = steps.copy()
    steps.loc[steps.index[:3], "settle_s"] = 0.0  # interleaved steps keep all their samples
    data = session_from_tables(KEY, steps, s, md)
    sm, warnings = average_session(data, min_samples=2)
    assert warnings == []
    _assert_matches_naive(sm, _naive(steps, s))


def test_replaced_gyro_or_accel_is_used_not_the_stale_channel_array():
    steps, samples, md = _simulate(32)
    data = session_from_tables(KEY, steps, samples, md)
    base, _ = average_session(data)
    shifted = dataclasses.replace(data, gyro=data.gyro + 5.0, accel=data.accel * 2.0)
    assert shifted.channels is data.channels  # stale: the averaging must notice
    moved, _ = average_session(shifted)
    np.testing.assert_allclose(moved.gyro, base.gyro + 5.0, rtol=1e-12)
    np.testing.assert_allclose(moved.accel, base.accel * 2.0, rtol=1e-12)
    np.testing.assert_allclose(moved.gyro_std, base.gyro_std, rtol=1e-9)
    # and without any of the reader's derived forms, the same numbers as with them
    plain, _ = average_session(dataclasses.replace(data, channels=None, step_columns=None, step_row=None))
    for f in (
        "gyro",
        "accel",
        "gyro_std",
        "accel_std",
        "count",
        "t_mid",
        "step",
        "test",
        "up_axis",
        "w_ref",
        "f_ref",
        "angle_deg",
    ):
        np.testing.assert_array_equal(getattr(plain, f), getattr(base, f))
        assert getattr(plain, f).dtype == getattr(base, f).dtype


def test_cached_steps_are_shared_read_only_and_results_are_private(tmp_path):
    steps, samples, md = _simulate(33)
    ref1 = SessionRef(KEY, write_session(tmp_path, KEY, steps, samples, md))
    key2 = SessionKey("L1", "U1", 2)
    ref2 = SessionRef(key2, write_session(tmp_path, key2, steps, samples, md))
    first = read_session(ref1)
    second = read_session(ref2)
    assert first.step_columns is second.step_columns  # one cache entry for equal bytes
    assert not first.step_columns.rate_dps.flags.writeable
    first.steps.loc[0, "rate_dps"] = 12345.0  # a caller changing its frame ...
    assert read_session(ref2).steps.loc[0, "rate_dps"] != 12345.0  # ... changes no other
    sm, _ = read_step_means(ref1)
    assert sm.rate_dps.flags.writeable and sm.w_ref.flags.writeable
    sm.rate_dps[0] = 999.0  # a result is the caller's own
    assert first.step_columns.rate_dps[0] != 999.0
    assert sm.test.dtype.kind == "U" and sm.step.dtype == np.int64 and sm.count.dtype == np.int64


def _force_exact_saturation_rules(monkeypatch):
    monkeypatch.setattr(averaging, "_may_saturate", lambda *a, **k: True)


def _case_clip_in_settling(samples, steps):
    """The session's extreme sits in left-out settling samples, repeated: not saturated."""
    s = samples.copy()
    first = s.index[s["step"] == int(steps["step"].iloc[5])][:3]
    s.loc[first, "gx"] = 349.0
    return s


def _case_clip_kept(samples, steps):
    """A kept pile-up at the session's extreme: clipped."""
    s = samples.copy()
    rows = s.index[s["step"] == int(steps["step"].iloc[5])][-10:]
    s.loc[rows, "gy"] = -349.0
    return s


def _case_clip_kept_beyond_a_settling_transient(samples, steps):
    """The session's extreme is a left-out transient; the kept extreme below it piles up:
    clipped (the kept extreme is reduced over the kept segments)."""
    s = _case_clip_kept(samples, steps)
    s.loc[s.index[s["step"] == int(steps["step"].iloc[9])][0], "gy"] = -349.5
    return s


def _case_full_scale_in_settling(samples, steps):
    """The declared full scale reached only while settling: not saturated."""
    s = samples.copy()
    s.loc[s.index[s["step"] == int(steps["step"].iloc[7])][0], "az"] = 60.0
    return s


def _case_full_scale_kept(samples, steps):
    s = samples.copy()
    s.loc[s.index[s["step"] == int(steps["step"].iloc[7])][-1], "az"] = -50.0
    return s


@pytest.mark.parametrize(
    "case",
    [
        _case_clip_in_settling,
        _case_clip_kept,
        _case_clip_kept_beyond_a_settling_transient,
        _case_full_scale_in_settling,
        _case_full_scale_kept,
    ],
)
def test_saturation_precheck_agrees_with_the_exact_rules(monkeypatch, case):
    steps, samples, md = _simulate(34)
    md = dict(md, gyro_range_dps="350,350,4000", accel_range_g="50,50,50")
    s = case(samples, steps)
    fast, w_fast = average_session(session_from_tables(KEY, steps, s, md))
    _force_exact_saturation_rules(monkeypatch)
    exact, w_exact = average_session(session_from_tables(KEY, steps, s, md))
    assert [str(w) for w in w_fast] == [str(w) for w in w_exact]
    np.testing.assert_array_equal(fast.step, exact.step)
    saturated = {w.step for w in w_exact}
    if case in (_case_clip_kept, _case_clip_kept_beyond_a_settling_transient, _case_full_scale_kept):
        assert len(saturated) == 1  # the case is what it claims to be
    else:
        assert saturated == set()


@pytest.mark.parametrize("seed", [35, 36])
def test_saturation_precheck_on_quantised_raw_data(monkeypatch, seed):
    """LSB data repeat their extreme codes: the pre-check hands over to the exact rules."""
    base = sim.typical_truth(np.random.default_rng(seed))
    truth = dataclasses.replace(
        base,
        K_g=base.K_g / 16.4,
        gyro_unit="LSB",
        gyro_quantum=1.0,
        K_a=base.K_a / 2048.0,
        accel_unit="LSB",
        accel_quantum=1.0,
    )
    steps = protocols.default_session(duration_s=1.0, settle_s=0.2)
    rng = np.random.default_rng(seed)
    samples = sim.simulate_session(truth, steps, rng, RATE)
    md = sim.session_metadata(truth, RATE)
    data = session_from_tables(KEY, steps, samples, md)
    x = data.channels
    assert averaging._may_saturate(
        x[:3],
        np.array([0]),  # one segment: every sample
        None,
    )  # repeated extremes: exact rules
    fast, w_fast = average_session(data)
    _force_exact_saturation_rules(monkeypatch)
    exact, w_exact = average_session(data)
    assert [str(w) for w in w_fast] == [str(w) for w in w_exact]
    np.testing.assert_array_equal(fast.gyro, exact.gyro)


def test_large_offsets_keep_the_small_standard_deviation():
    """3600 deg/s and 32768 LSB means with noise far below them: the two-pass standard
    deviation matches an fsum computation (a one-pass sum of squares would lose ~7 digits)."""
    steps, samples, md = _simulate(37, settle_s=0.0)
    rng = np.random.default_rng(37)
    s = samples.copy()
    n = len(s)
    s["gz"] = 3600.0 + rng.normal(0, 1e-3, n)
    s["ax"] = 32768.0 + rng.normal(0, 0.5, n)
    s["gx"] = -3600.0 + rng.normal(0, 1e-4, n)
    for c in ("gz", "ax", "gx"):
        s[c] = s[c].astype(np.float64)  # float64 columns (float32 would quantise the noise)
    md = dict(md, gyro_unit="LSB", accel_unit="LSB")
    sm, _ = average_session(session_from_tables(KEY, steps, s, md))
    _assert_matches_naive(sm, _naive(steps, s), rtol=1e-15)


def test_nonfinite_found_by_the_one_pass_check_gives_the_column_error():
    steps, samples, md = _simulate(38)
    s = samples.copy()
    gz = s["gz"].to_numpy(np.float64)
    gz[17] = np.inf
    ax = s["ax"].to_numpy(np.float64)
    ax[3] = np.nan
    s["gz"], s["ax"] = gz, ax
    with pytest.raises(SessionError) as info:
        session_from_tables(KEY, steps, s, md)
    assert info.value.code == E_NONFINITE_VALUE and info.value.column == "gz"  # gx..az order
    assert "1 infinite" in str(info.value) and "row 17" in str(info.value)


def test_finite_values_whose_sum_overflows_are_not_an_error():
    """The one-pass check sums each channel; an overflowing sum of finite values goes to the
    exact search, which finds nothing to report (as before the change)."""
    steps, samples, md = _simulate(39)
    s = samples.copy()
    big = np.full(len(s), 1e307)
    big[::2] = 1.7e308
    s["gx"] = big
    data = session_from_tables(KEY, steps, s, md)
    assert np.isfinite(data.gyro).all() and data.gyro[0, 0] == 1.7e308


def test_int64_step_ids_take_the_range_checked_path():
    steps, samples, md = _simulate(40)
    table = pa.Table.from_pandas(samples.astype({"step": np.int64}), preserve_index=False)
    assert table.schema.field("step").type == pa.int64()
    a, _ = average_session(session_from_tables(KEY, steps, table, md))
    b, _ = average_session(session_from_tables(KEY, steps, samples, md))
    np.testing.assert_array_equal(a.gyro, b.gyro)
    np.testing.assert_array_equal(a.count, b.count)


@pytest.mark.parametrize("seed", [40, 41, 42])
def test_settling_search_equals_the_rule_on_every_sample(seed):
    """The kept suffix of each run found by searchsorted and the exact rule's corrections
    equals the rule evaluated on every sample, also where t0 + settle_s rounds across a
    sample (times that are not multiples of the sample period, settle_s at sample times,
    samples a few ulp apart)."""
    rng = np.random.default_rng(seed)
    n_runs = 200
    lengths = rng.integers(1, 40, n_runs)
    dt = rng.choice([1e-2, 1 / 3, 1e-9, 5e-16], n_runs)  # the last: a few ulp at t ~ 1
    steps_t = [1.0 + np.cumsum(np.full(k, d)) for k, d in zip(lengths, dt)]
    t = np.concatenate(steps_t)
    t += np.arange(len(t)) * 1e-12  # strictly increasing across the runs
    end = np.cumsum(lengths)
    start = end - lengths
    t0 = t[start]
    # thresholds at, just below and just above sample offsets, zero and beyond the run
    pick = np.minimum(rng.integers(0, 45, n_runs), lengths - 1)
    offset = t[start + pick] - t0
    threshold = offset * rng.choice([1.0, 1 - 1e-16, 1 + 1e-16, 0.0, 10.0], n_runs) - 1e-6
    exact = segments.settled_per_sample(t, start, end, t0, threshold)
    found = segments.settled_from(t, start, end, t0, threshold)
    if found is not None:
        np.testing.assert_array_equal(found, exact)
    for r in range(n_runs):  # the exact answer is the rule's suffix
        kept = t[start[r] : end[r]] - t0[r] >= threshold[r]
        assert kept.sum() == end[r] - exact[r] and kept[exact[r] - start[r] :].all()


def test_settling_fallback_gives_the_same_step_means(monkeypatch):
    """With the search given no moves (every sample evaluated) the results are identical."""
    steps, samples, md = _simulate(43, temperature=True)
    fast, w_fast = average_session(session_from_tables(KEY, steps, samples, md), min_samples=2)
    monkeypatch.setattr(segments, "SETTLE_SEARCH_STEPS", 0)
    slow, w_slow = average_session(session_from_tables(KEY, steps, samples, md), min_samples=2)
    assert [str(w) for w in w_fast] == [str(w) for w in w_slow]
    for f in ("step", "gyro", "accel", "gyro_std", "accel_std", "count", "t_mid", "temp_c"):
        np.testing.assert_array_equal(getattr(fast, f), getattr(slow, f))


def test_one_stat_answers_missing_not_regular_and_empty(tmp_path):
    from schemas import reader
    from schemas.errors import E_MISSING_FILE, E_UNREADABLE_FILE

    (tmp_path / "dir.parquet").mkdir()
    (tmp_path / "empty.parquet").write_bytes(b"")
    (tmp_path / "file").write_bytes(b"x")
    cases = {
        "nothing.parquet": E_MISSING_FILE,
        "dir.parquet": E_UNREADABLE_FILE,
        "empty.parquet": E_UNREADABLE_FILE,
        "file/below.parquet": E_MISSING_FILE,
    }
    for name, code in cases.items():
        path = tmp_path / name
        assert (reader._stat(path) is None) == (not path.exists())
        with pytest.raises(SessionError) as info:
            reader._open(path, "s")
        assert info.value.code == code
    assert reader._stat(tmp_path / "a\0b") is None  # as Path.exists: False, no error


@pytest.mark.parametrize("seed", [44, 45])
def test_kept_reach_bounds_every_kept_sample(seed):
    """The saturation pre-check's bound from the steps' means and squared deviations is at
    least the largest |x| of the samples the settling rule keeps (pandas' selection), also
    with large offsets and a lone spike, and not far above it on a calm channel."""
    steps, samples, md = _simulate(seed)
    rng = np.random.default_rng(seed)
    s = samples.copy()
    s["gz"] = 3600.0 + rng.normal(0, 1e-3, len(s))  # a large mean, tiny deviations
    s.loc[s.index[s["step"] == int(steps["step"].iloc[4])][-1], "ax"] = 7.5  # one kept spike
    for c in ("gz", "ax"):
        s[c] = s[c].astype(np.float64)
    data = session_from_tables(KEY, steps, s, md)
    sm, _ = average_session(data, min_samples=2)
    settle = dict(zip(steps["step"], steps["settle_s"]))
    kept = []
    for step_id, g in s[s["step"] != -1].groupby("step"):
        kept.append(g[g["t"] - g["t"].iloc[0] >= settle[step_id] - 1e-6])
    kept = pd.concat(kept)
    x = np.stack([kept[c].to_numpy(np.float64) for c in CHANNELS])
    mean = np.concatenate([sm.gyro.T, sm.accel.T])
    std = np.concatenate([sm.gyro_std.T, sm.accel_std.T])
    sq_dev = std**2 * (sm.count - 1)
    reach = averaging._kept_reach(mean, sq_dev)
    largest = np.abs(x).max(axis=1)
    assert (reach >= largest).all()
    assert reach[2] < 3600.1  # gz: the offset and a few noise sd, not a multiple of it
