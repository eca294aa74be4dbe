"""Every invalid case of the contract gives its stable code and a message that names the
session, the file and the reason. Bad sessions are made from a good simulated one in tmp_path."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from calib_core.errors import DesignError
from calib_core.sim import protocols
from calib_core.sim import simulator as sim
from calib_core.steps import SessionKey
from schemas import errors as E
from schemas.averaging import read_step_means
from schemas.contract import SAMPLES_SCHEMA, STEPS_SCHEMA, parse_metadata, parse_triple
from schemas.dataset import SessionRef
from schemas.errors import SessionError, from_design_error
from schemas.reader import read_session
from schemas.writer import write_session

RATE = 50.0
KEY = SessionKey("L1", "U001", 2)


@pytest.fixture
def good(tmp_path):
    rng = np.random.default_rng(42)
    truth = sim.typical_truth(rng)
    steps = protocols.default_session(duration_s=1.0, settle_s=0.2)
    samples = sim.simulate_session(truth, steps, rng, RATE)
    md = sim.session_metadata(truth, RATE)
    path = write_session(tmp_path, KEY, steps, samples, md)
    return SessionRef(KEY, path)


def read_table(path):
    return pq.ParquetFile(path).read()


def rewrite(path, fn):
    pq.write_table(fn(read_table(path)), path)


def replace_column(table: pa.Table, name: str, array) -> pa.Table:
    i = table.schema.get_field_index(name)
    return table.set_column(i, name, array)


def set_metadata(path, **changes):
    def fn(t):
        md = {k.decode(): v.decode() for k, v in (t.schema.metadata or {}).items()}
        for k, v in changes.items():
            if v is None:
                md.pop(k, None)
            else:
                md[k] = v
        return t.replace_schema_metadata(md)

    rewrite(path, fn)


def expect_error(ref, code, file, *reason_parts, column=None, step=None) -> SessionError:
    with pytest.raises(SessionError) as info:
        read_step_means(ref)
    err = info.value
    msg = str(err)
    assert err.code == code, msg
    assert err.session == str(ref.key) and str(ref.key) in msg
    assert err.file == file and file in msg
    for part in reason_parts:
        assert part in msg, f"{part!r} not in {msg!r}"
    if column is not None:
        assert err.column == column and f"column {column}" in msg
    if step is not None:
        assert err.step == step and f"step {step}" in msg
    print(msg)  # the docs' table of messages is copied from this output (pytest -s)
    return err


def test_good_session_reads_without_warnings(good):
    sm, warnings = read_step_means(good)
    assert warnings == []
    assert len(sm) == 118 and sm.key == KEY


# --- files -----------------------------------------------------------------------------------
def test_missing_samples_file(good):
    good.samples_path.unlink()
    expect_error(good, E.E_MISSING_FILE, "samples.parquet", "samples.parquet missing")


def test_missing_steps_file(good):
    good.steps_path.unlink()
    expect_error(good, E.E_MISSING_FILE, "steps.parquet", "steps.parquet missing")


def test_zero_byte_file(good):
    good.samples_path.write_bytes(b"")
    expect_error(good, E.E_UNREADABLE_FILE, "samples.parquet", "empty (0 bytes)")


def test_truncated_file(good):
    data = good.steps_path.read_bytes()
    good.steps_path.write_bytes(data[: len(data) - 100])
    expect_error(good, E.E_UNREADABLE_FILE, "steps.parquet", "not a readable Parquet file")


def test_corrupted_data_pages(good):
    # garbage over the compressed data pages (after the 4-byte magic, before the footer)
    data = bytearray(good.samples_path.read_bytes())
    rng = np.random.default_rng(0)
    data[100:20100] = rng.integers(0, 256, 20000, dtype=np.uint8).tobytes()
    good.samples_path.write_bytes(bytes(data))
    # the simulator's files carry page checksums: the damage is named as such
    expect_error(good, E.E_CHECKSUM, "samples.parquet", "checksum does not match")


def test_not_parquet_at_all(good):
    good.samples_path.write_text("step,t,gx\n0,0.0,1.0\n")
    expect_error(good, E.E_UNREADABLE_FILE, "samples.parquet", "not a readable Parquet file")


# --- columns and types -------------------------------------------------------------------------
def test_missing_sensor_column(good):
    rewrite(good.samples_path, lambda t: t.drop_columns(["gz"]))
    expect_error(good, E.E_MISSING_COLUMN, "samples.parquet", "required column 'gz' is missing", column="gz")


def test_missing_steps_column(good):
    rewrite(good.steps_path, lambda t: t.drop_columns(["settle_s"]))
    expect_error(good, E.E_MISSING_COLUMN, "steps.parquet", "'settle_s' is missing", column="settle_s")


def test_extra_columns_are_ignored(good):
    before, _ = read_step_means(good)
    rewrite(
        good.samples_path, lambda t: t.append_column("mag_x", pa.array([f"x{i}" for i in range(t.num_rows)]))
    )
    rewrite(good.steps_path, lambda t: t.append_column("operator", pa.array(["A"] * t.num_rows)))
    after, warnings = read_step_means(good)
    assert warnings == []
    np.testing.assert_array_equal(after.gyro, before.gyro)


@pytest.mark.parametrize(
    "file,column,array_of,expected",
    [
        ("samples", "gx", lambda t: pa.array(t["gx"].to_numpy().astype(str)), "float32 or float64"),
        ("samples", "t", lambda t: pa.array(np.arange(t.num_rows, dtype=np.int64)), "float64"),
        ("samples", "step", lambda t: pa.array(t["step"].to_numpy().astype(np.float64)), "int32"),
        ("steps", "test", lambda t: pa.array(np.arange(t.num_rows, dtype=np.int32)), "string"),
        ("steps", "rate_dps", lambda t: pa.array(t["rate_dps"].to_numpy().astype(str)), "float64"),
    ],
)
def test_wrong_type(good, file, column, array_of, expected):
    path = good.samples_path if file == "samples" else good.steps_path
    rewrite(path, lambda t: replace_column(t, column, array_of(t)))
    expect_error(
        good, E.E_WRONG_TYPE, path.name, f"column '{column}' has type", f"expected {expected}", column=column
    )


def test_lenient_types_are_accepted(good):
    """int64 step ids, float32 time and float64 sensors are read (nothing can be lost)."""
    before, _ = read_step_means(good)

    def widen(t):
        t = replace_column(t, "step", pa.array(t["step"].to_numpy().astype(np.int64)))
        return replace_column(t, "gx", pa.array(t["gx"].to_numpy().astype(np.float64)))

    rewrite(good.samples_path, widen)
    after, warnings = read_step_means(good)
    assert warnings == []
    np.testing.assert_array_equal(after.gyro, before.gyro)


# --- metadata -----------------------------------------------------------------------------------
def test_unknown_gyro_unit(good):
    set_metadata(good.samples_path, gyro_unit="dps")
    expect_error(good, E.E_UNKNOWN_UNIT, "samples.parquet", "gyro_unit 'dps' is not one of")


def test_unknown_accel_unit(good):
    set_metadata(good.samples_path, accel_unit="m/s2")
    expect_error(good, E.E_UNKNOWN_UNIT, "samples.parquet", "accel_unit 'm/s2' is not one of")


def test_unparseable_range(good):
    set_metadata(good.samples_path, gyro_range_dps="300;300;3600")
    expect_error(
        good, E.E_BAD_METADATA, "samples.parquet", "gyro_range_dps", "not a comma-separated list of numbers"
    )


def test_range_with_wrong_count(good):
    set_metadata(good.samples_path, accel_range_g="50,50")
    expect_error(good, E.E_BAD_METADATA, "samples.parquet", "accel_range_g", "2 values, expected 3")


def test_missing_unit_key(good):
    set_metadata(good.samples_path, gyro_unit=None)
    expect_error(good, E.E_BAD_METADATA, "samples.parquet", "'gyro_unit' is missing")


def test_g_local_in_g_not_m_s2(good):
    set_metadata(good.samples_path, g_local="1.0")
    expect_error(good, E.E_BAD_METADATA, "samples.parquet", "g_local", "outside")


def test_metadata_parsing():
    md = parse_metadata(
        {
            b"gyro_unit": b"rad/s",
            b"accel_unit": b"m/s^2",
            b"gyro_range_dps": b"300, 300, 3600",
            b"accel_range_g": b"16",
            b"operator": b"jd",
            b"pandas": b"{}",
        },
        "s",
    )
    assert md.gyro_range_dps == (300.0, 300.0, 3600.0)
    assert md.accel_range_g == (16.0, 16.0, 16.0)
    assert md.g_local == 9.80665  # default when absent
    assert md.sample_rate_hz is None
    assert md.gyro_unit == "deg/s" and md.accel_unit == "g"
    assert md.gyro_scale == pytest.approx(57.29577951308232)
    assert md.accel_scale == pytest.approx(1 / 9.80665)
    assert md.provenance == {
        "gyro_unit": "rad/s",
        "accel_unit": "m/s^2",
        "gyro_range_dps": "300, 300, 3600",
        "accel_range_g": "16",
        "operator": "jd",
    }
    with pytest.raises(SessionError, match="must be finite and positive"):
        parse_triple("300,-1,3600", "gyro_range_dps", "s", "samples.parquet")


# --- content --------------------------------------------------------------------------------------
def _with_values(t, column, rows, value):
    x = t[column].to_numpy().copy()
    x[rows] = value
    return replace_column(t, column, pa.array(x))


def test_nan_burst(good):
    rewrite(good.samples_path, lambda t: _with_values(t, "ay", slice(2000, 2020), np.nan))
    sample_step = int(read_table(good.samples_path)["step"][2000].as_py())
    expect_error(
        good,
        E.E_NONFINITE_VALUE,
        "samples.parquet",
        "20 NaN",
        "first at row 2000",
        column="ay",
        step=sample_step,
    )


def test_inf_value(good):
    rewrite(good.samples_path, lambda t: _with_values(t, "gz", [500], np.inf))
    expect_error(good, E.E_NONFINITE_VALUE, "samples.parquet", "1 infinite", column="gz")


def test_null_value(good):
    def fn(t):
        x = t["ax"].to_numpy()
        mask = np.zeros(len(x), bool)
        mask[100:103] = True
        return replace_column(t, "ax", pa.array(x, mask=mask))

    rewrite(good.samples_path, fn)
    expect_error(good, E.E_NONFINITE_VALUE, "samples.parquet", "3 null", column="ax")


def test_nan_time(good):
    rewrite(good.samples_path, lambda t: _with_values(t, "t", [10], np.nan))
    expect_error(good, E.E_NONFINITE_VALUE, "samples.parquet", "time is nan", column="t")


def test_nonincreasing_time(good):
    def fn(t):
        x = t["t"].to_numpy().copy()
        x[1000], x[1001] = x[1001], x[1000]
        return replace_column(t, "t", pa.array(x))

    rewrite(good.samples_path, fn)
    expect_error(
        good, E.E_NONINCREASING_TIME, "samples.parquet", "not strictly increasing", "row 1001", column="t"
    )


def test_repeated_time_is_not_increasing(good):
    def fn(t):
        x = t["t"].to_numpy().copy()
        x[3001] = x[3000]
        return replace_column(t, "t", pa.array(x))

    rewrite(good.samples_path, fn)
    expect_error(good, E.E_NONINCREASING_TIME, "samples.parquet", "row 3001")


def test_duplicate_step_ids(good):
    def fn(t):
        s = t["step"].to_numpy().copy()
        s[7] = s[6]
        return replace_column(t, "step", pa.array(s))

    rewrite(good.steps_path, fn)
    expect_error(
        good, E.E_DUPLICATE_STEP, "steps.parquet", "step id 6 appears 2 times", column="step", step=6
    )


def test_unknown_step_in_samples(good):
    def fn(t):
        s = t["step"].to_numpy().copy()
        s[s == 5] = 999
        return replace_column(t, "step", pa.array(s))

    rewrite(good.samples_path, fn)
    expect_error(good, E.E_UNKNOWN_STEP, "samples.parquet", "step id 999 is not in steps.parquet", step=999)


@pytest.mark.parametrize(
    "column,value,reason",
    [
        ("test", "spin", "test 'spin' is not one of"),
        ("up_axis", "up", "up_axis 'up' is not one of"),
        ("w_ref_y", np.nan, "w_ref_y is nan"),
        ("settle_s", -1.0, "settle_s is -1.0"),
    ],
)
def test_bad_step_definition(good, column, value, reason):
    rewrite(good.steps_path, lambda t: _with_values(t, column, [3], value))
    expect_error(good, E.E_BAD_STEP_DEFINITION, "steps.parquet", reason, column=column, step=3)


def test_reserved_step_id(good):
    def fn(t):
        s = t["step"].to_numpy().copy()
        s[0] = -1
        return replace_column(t, "step", pa.array(s))

    rewrite(good.steps_path, fn)
    expect_error(good, E.E_BAD_STEP_DEFINITION, "steps.parquet", "reserved", step=-1)


def test_empty_samples(good):
    rewrite(good.samples_path, lambda t: t.slice(0, 0))
    expect_error(good, E.E_EMPTY_SESSION, "samples.parquet", "no rows")


def test_empty_steps(good):
    rewrite(good.steps_path, lambda t: t.slice(0, 0))
    expect_error(good, E.E_EMPTY_SESSION, "steps.parquet", "no rows")


def test_no_usable_step(good):
    rewrite(good.steps_path, lambda t: replace_column(t, "settle_s", pa.array(np.full(t.num_rows, 5.0))))
    expect_error(good, E.E_EMPTY_SESSION, "samples.parquet", "no usable step left", "118 W_TOO_SHORT")


# --- design errors and the error types -----------------------------------------------------------
def test_from_design_error_names_session_and_what_is_undetermined():
    exc = DesignError("E_RANK", "no rotation about x", undetermined=("k_g11", "k_g21"))
    err = from_design_error(exc, str(KEY), "steps.parquet")
    msg = str(err)
    assert err.code == E.E_UNDETERMINED
    assert str(KEY) in msg and "steps.parquet" in msg
    assert "no rotation about x" in msg and "k_g11, k_g21" in msg and "E_RANK" in msg
    assert err.__cause__ is exc
    print(msg)


def test_session_error_pickles_and_serialises():
    import pickle

    err = SessionError(E.E_MISSING_COLUMN, str(KEY), "samples.parquet", "gone", column="gz", step=3)
    back = pickle.loads(pickle.dumps(err))
    assert str(back) == str(err) and back.column == "gz" and back.step == 3
    assert err.to_dict()["message"] == str(err)


def test_schemas_are_the_contract():
    assert STEPS_SCHEMA.names == [
        "step",
        "test",
        "up_axis",
        "rate_dps",
        "angle_deg",
        "w_ref_x",
        "w_ref_y",
        "w_ref_z",
        "f_ref_x",
        "f_ref_y",
        "f_ref_z",
        "settle_s",
    ]
    assert STEPS_SCHEMA.field("step").type == pa.int32()
    assert SAMPLES_SCHEMA.names == ["step", "t", "gx", "gy", "gz", "ax", "ay", "az"]
    assert SAMPLES_SCHEMA.field("t").type == pa.float64()


def test_read_session_converts_units_at_the_boundary(good, tmp_path):
    """A rad/s file is deg/s inside: the converted values equal the deg/s ones."""
    base = read_session(good)
    t = read_table(good.samples_path)
    md = {k.decode(): v.decode() for k, v in t.schema.metadata.items()}
    md["gyro_unit"] = "rad/s"
    t2 = replace_column(t, "gx", pa.array(t["gx"].to_numpy().astype(np.float64) * np.pi / 180))
    pq.write_table(t2.replace_schema_metadata(md), good.samples_path)
    conv = read_session(good)
    np.testing.assert_allclose(conv.gyro[:, 0], base.gyro[:, 0], rtol=1e-12, atol=1e-12)
    assert conv.meta.gyro_unit == "deg/s" and conv.meta.gyro_unit_raw == "rad/s"
