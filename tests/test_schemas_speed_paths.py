"""The speed paths of the reader and the averaging (docs/benchmarks.md) give the same answers
as the plain paths: the steps-table cache, the sample -> step lookup table and its binary
search fallback, and the run-based first/last sample times."""

from __future__ import annotations

import dataclasses

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from calib_core.sim import protocols
from calib_core.sim import simulator as sim
from calib_core.steps import SessionKey
from schemas import reader
from schemas.averaging import average_session
from schemas.dataset import SessionRef
from schemas.errors import E_BAD_STEP_DEFINITION, E_UNKNOWN_STEP, SessionError
from schemas.reader import read_session, read_steps, session_from_tables
from schemas.writer import write_session

RATE = 20.0
KEY = SessionKey("L1", "U1", 1)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    rng = np.random.default_rng(11)
    truth = sim.typical_truth(rng)
    steps = protocols.default_session(duration_s=1.0, settle_s=0.2)
    samples = sim.simulate_session(truth, steps, rng, RATE)
    md = sim.session_metadata(truth, RATE)
    root = tmp_path_factory.mktemp("speed")
    return steps, samples, md, SessionRef(KEY, write_session(root, KEY, steps, samples, md))


def test_cached_steps_are_a_private_copy(session):
    _, _, _, ref = session
    first = read_steps(ref.steps_path, "a")
    first.loc[0, "rate_dps"] = 12345.0  # a caller mutating its frame
    first["test"] = "multirate"
    second = read_steps(ref.steps_path, "b")
    assert second.loc[0, "rate_dps"] != 12345.0
    assert (second["test"] != "multirate").any()
    assert second.dtypes.equals(read_steps(ref.steps_path, "c").dtypes)
    assert str(second["test"].dtype) == "string"


def test_a_changed_steps_file_is_validated_again(session, tmp_path):
    steps, samples, md, _ = session
    ref = SessionRef(KEY, write_session(tmp_path, KEY, steps, samples, md))
    read_steps(ref.steps_path, "warm")  # the good table is now cached
    bad = pq.read_table(ref.steps_path)
    settle = bad.column("settle_s").to_numpy().copy()
    settle[3] = -1.0
    bad = bad.set_column(bad.schema.get_field_index("settle_s"), "settle_s", pa.array(settle))
    pq.write_table(bad, ref.steps_path)
    with pytest.raises(SessionError) as exc:
        read_steps(ref.steps_path, str(KEY))
    assert exc.value.code == E_BAD_STEP_DEFINITION and "settle_s" in str(exc.value)
    # and an error is never cached: the same bad bytes fail again
    with pytest.raises(SessionError):
        read_steps(ref.steps_path, str(KEY))


def _naive_rows(step: np.ndarray, ids: np.ndarray) -> np.ndarray:
    pos = {int(s): i for i, s in enumerate(ids)}
    return np.array([-1 if s == -1 else pos.get(int(s), -2) for s in step])


@pytest.mark.parametrize("offset", [0, 5_000_000, -1_000])  # lookup table, binary search
def test_step_rows_match_a_dictionary_lookup(offset):
    rng = np.random.default_rng(3)
    ids = rng.permutation(np.arange(40)) * 3 + offset
    ids = ids[ids != -1]
    step = rng.choice(np.append(ids, [-1, offset + 1, offset + 2]), size=2000)
    np.testing.assert_array_equal(reader._step_rows(step, ids), _naive_rows(step, ids))


def test_unknown_step_with_large_ids_is_reported(session):
    steps, samples, md, _ = session
    steps = steps.copy()
    samples = samples.copy()
    steps["step"] = steps["step"] + 5_000_000
    known = samples["step"].to_numpy() >= 0
    new = samples["step"].to_numpy().copy()
    new[known] += 5_000_000
    new[np.flatnonzero(known)[:7]] = 4_999_999  # not in steps.parquet
    samples["step"] = new
    with pytest.raises(SessionError) as exc:
        session_from_tables(KEY, steps, samples, md)
    assert exc.value.code == E_UNKNOWN_STEP and exc.value.step == 4_999_999
    assert "7 sample(s)" in str(exc.value)


def test_averaging_is_the_same_with_and_without_the_readers_index(session):
    _, _, _, ref = session
    data = read_session(ref)
    assert data.step_row is not None
    fast, w_fast = average_session(data)
    slow, w_slow = average_session(dataclasses.replace(data, step_row=None))
    for f in ("step", "gyro", "accel", "gyro_std", "accel_std", "count", "t_mid"):
        np.testing.assert_array_equal(getattr(fast, f), getattr(slow, f))
    assert [str(w) for w in w_fast] == [str(w) for w in w_slow]


def test_first_and_last_times_of_interleaved_steps(session):
    """A step split into several runs (by between-step samples, id -1, inside it) still
    gets its first and last sample times: compare t_mid with a per-step min/max computed by
    pandas."""
    steps, samples, md, _ = session
    steps = steps.copy()
    steps["settle_s"] = 0.0
    s = samples.copy()
    ids = s["step"].to_numpy().copy()
    a, b = int(steps["step"].iloc[0]), int(steps["step"].iloc[1])
    rows = np.flatnonzero((ids == a) | (ids == b))
    ids[rows[1::3]] = -1  # a and b now come in short runs
    s["step"] = ids
    sm, _ = average_session(session_from_tables(KEY, steps, s, md), min_samples=2)
    kept = s[s["step"] >= 0]
    g = kept.groupby("step")["t"].agg(["min", "max"])
    expected = ((g["min"] + g["max"]) / 2).reindex(sm.step).to_numpy()
    np.testing.assert_allclose(sm.t_mid, expected, rtol=0, atol=1e-12)
    counts = kept.groupby("step").size().reindex(sm.step).to_numpy()
    np.testing.assert_array_equal(sm.count, counts)
