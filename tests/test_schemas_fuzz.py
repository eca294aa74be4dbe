"""Property-based: any corruption of a session's files or tables gives a SessionError with a
known code, or usable step means that are all finite; never another exception."""

from __future__ import annotations

import shutil

import numpy as np
import pyarrow as pa
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from calib_core.sim import protocols
from calib_core.sim import simulator as sim
from calib_core.steps import SessionKey
from schemas.averaging import read_step_means, step_means_from_tables
from schemas.dataset import SessionRef
from schemas.errors import ERROR_CODES, WARNING_CODES, SessionError
from schemas.writer import write_session

KEY = SessionKey("L1", "U001", 1)
STEPS = protocols.default_session(duration_s=1.0, settle_s=0.2, dynamic=False)
_RNG = np.random.default_rng(0)
TRUTH = sim.typical_truth(_RNG)
SAMPLES = sim.simulate_session(TRUTH, STEPS, _RNG, 10.0)
MD = sim.session_metadata(TRUTH, 10.0)


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    root = tmp_path_factory.mktemp("pristine")
    return write_session(root, KEY, STEPS, SAMPLES, MD)


def check_outcome(call):
    try:
        sm, warnings = call()
    except SessionError as exc:
        assert exc.code in ERROR_CODES
        assert str(KEY) in str(exc) and exc.reason
        return "error"
    assert len(sm) > 0
    for name in ("gyro", "accel", "gyro_std", "accel_std", "w_ref", "f_ref", "t_mid"):
        assert np.isfinite(getattr(sm, name)).all(), name
    assert all(w.code in WARNING_CODES for w in warnings)
    return "ok"


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    which=st.sampled_from(["samples.parquet", "steps.parquet"]),
    where=st.floats(0, 1),
    length=st.integers(1, 64),
    seed=st.integers(0, 2**32 - 1),
    truncate=st.booleans(),
)
def test_byte_corruption_is_an_error_or_finite(
    pristine, tmp_path_factory, which, where, length, seed, truncate
):
    work = tmp_path_factory.mktemp("bytes") / "lot=L1/unit=U001/rep=1"
    shutil.copytree(pristine, work)
    path = work / which
    data = bytearray(path.read_bytes())
    at = int(where * (len(data) - 1))
    if truncate:
        data = data[:at]
    else:
        noise = np.random.default_rng(seed).integers(0, 256, length, dtype=np.uint8).tobytes()
        data[at : at + length] = noise[: len(data) - at]
    path.write_bytes(bytes(data))
    check_outcome(lambda: read_step_means(SessionRef(KEY, work)))


@settings(max_examples=80, deadline=None)
@given(
    column=st.sampled_from(["step", "t", "gx", "gy", "gz", "ax", "ay", "az"]),
    rows=st.lists(st.integers(0, len(SAMPLES) - 1), min_size=1, max_size=20),
    value=st.sampled_from([np.nan, np.inf, -np.inf, 0.0, -1.0, 1e30, 7.0, 12345.0]),
    drop=st.booleans(),
)
def test_table_mutations_are_an_error_or_finite(column, rows, value, drop):
    samples = SAMPLES.copy()
    if drop:
        samples = samples.drop(columns=[column])
    else:
        x = samples[column].to_numpy(copy=True)
        if column == "step":
            x[rows] = np.int32(int(value) if np.isfinite(value) and abs(value) < 2**31 else 99)
        else:
            x[rows] = value
        samples[column] = x
    table = pa.Table.from_arrays(
        [pa.array(samples[c].to_numpy()) for c in samples.columns], names=list(samples.columns)
    )
    check_outcome(lambda: step_means_from_tables(KEY, STEPS, table, MD))


@pytest.mark.slow
@settings(max_examples=40, deadline=None)
@given(
    key=st.sampled_from(
        [
            "gyro_unit",
            "accel_unit",
            "gyro_range_dps",
            "accel_range_g",
            "g_local",
            "sample_rate_hz",
            "gyro_full_scale_raw",
        ]
    ),
    value=st.text(max_size=12),
)
def test_metadata_mutations_are_an_error_or_finite(key, value):
    md = dict(MD, **{key: value})
    check_outcome(lambda: step_means_from_tables(KEY, STEPS, pa.Table.from_pandas(SAMPLES), md))
