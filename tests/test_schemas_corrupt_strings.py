"""A steps table whose string column holds bytes that are not UTF-8 (a corrupt file: found
by tests/test_schemas_fuzz.py, one flipped byte of steps.parquet) is a SessionError naming
the column, not an ArrowException."""

from __future__ import annotations

import pyarrow as pa
import pytest

from calib_core.sim import protocols
from schemas.errors import E_UNREADABLE_FILE, SessionError
from schemas.reader import validate_steps


def _with_invalid_utf8(table: pa.Table, column: str) -> pa.Table:
    good = table.column(column).combine_chunks()
    data = bytearray(good.buffers()[2].to_pybytes())
    data[3] = 0xFF  # never valid in UTF-8
    offsets = good.buffers()[1]
    bad = pa.Array.from_buffers(pa.string(), len(good), [None, offsets, pa.py_buffer(bytes(data))])
    return table.set_column(table.schema.get_field_index(column), column, bad)


@pytest.mark.parametrize("column", ["test", "up_axis"])
def test_invalid_utf8_in_steps_is_a_session_error(column):
    steps = protocols.default_session(duration_s=1.0, settle_s=0.2, dynamic=False)
    table = pa.Table.from_pandas(steps, preserve_index=False)
    assert validate_steps(table, "lot=L/unit=U/rep=1") is not None  # the pristine table is fine
    with pytest.raises(SessionError) as info:
        validate_steps(_with_invalid_utf8(table, column), "lot=L/unit=U/rep=1")
    assert info.value.code == E_UNREADABLE_FILE
    assert column in str(info.value) and "lot=L/unit=U/rep=1" in str(info.value)
    assert "steps.parquet" in str(info.value)
