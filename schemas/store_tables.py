"""The declared Arrow schema of every results table (``tables/<name>/lot=<lot>.parquet``).

Every lot file of a table is written with its table's schema (:func:`conform`), so a table
directory reads as one table in any Parquet reader (``pandas.read_parquet(dir)``,
``pyarrow.dataset``, DuckDB): a column that is all null in one lot has the declared type
there too, not Arrow's ``null`` type. The store's verification (``ResultsStore.verify``)
checks each file against it; older files are rewritten with it by the first write
(``ResultsStore._migrate``).

A column a writer adds that is not declared here is kept after the declared ones (its
inferred type; all-null as string) and makes ``tests/test_store_schemas.py`` fail: declare
it here.
"""

from __future__ import annotations

import json

import pyarrow as pa

_S, _I, _F, _B = pa.large_string(), pa.int64(), pa.float64(), pa.bool_()
_F32 = pa.float32()


def _schema(*fields: tuple[str, pa.DataType]) -> pa.Schema:
    return pa.schema([pa.field(n, t) for n, t in fields])


_KEYS = (("lot", _S), ("unit", _S))

TABLE_SCHEMAS: dict[str, pa.Schema] = {
    "sessions": _schema(
        *_KEYS,
        ("rep", _I),
        ("status", _S),
        ("error_code", _S),
        ("message", _S),
        ("warnings", pa.list_(pa.string())),
        ("fingerprint", _S),
        ("run_id", _S),
        ("path", _S),
        ("calibrated_at", _S),
        # facts about the protocol, the same for every session of it (P_...): not warnings
        ("protocol_notes", pa.list_(pa.string())),
    ),
    "parameters": _schema(
        *_KEYS,
        ("rep", _I),
        ("model", _S),
        ("parameter", _S),
        ("value", _F),
        ("stderr", _F),
        ("unit_of_measure", _S),
        ("code_version", _S),
        ("run_id", _S),
    ),
    "summary": _schema(
        *_KEYS,
        ("model", _S),
        ("parameter", _S),
        ("mean", _F),
        ("std", _F),
        ("min", _F),
        ("max", _F),
        ("n_reps", _I),
        ("stderr_of_mean", _F),
        ("unit_of_measure", _S),
        ("flagged", _B),
        ("flag_reason", _S),
        ("score", _F),
        ("lot_median", _F),
        ("lot_scatter", _F),
        ("lot_median_std", _F),
        ("stale", _B),
        ("stale_reason", _S),
        ("run_id", _S),
    ),
    "units": _schema(
        *_KEYS,
        ("state", _S),
        ("reason", _S),
        ("error_code", _S),
        ("n_sessions", _I),
        ("n_ok", _I),
        ("n_warned", _I),
        ("n_failed", _I),
        ("calibration_file", _S),
        ("calibrated_at", _S),
        ("run_id", _S),
        ("updated_at", _S),
        ("flagged", _B),
        ("flag_reason", _S),
        ("acquired_at", _S),
    ),
    "residuals": _schema(
        *_KEYS,
        ("rep", _I),
        ("step", _I),
        ("test", _S),
        ("up_axis", _S),
        ("rate_dps", _F),
        ("angle_deg", _F),
        ("channel", _S),
        ("reference", _F),
        ("residual", _F),
        ("sigma", _F),
        ("model", _S),
    ),
    "compensation": _schema(
        *_KEYS,
        ("rep", _I),
        ("input_axis", _S),
        ("output_axis", _S),
        ("method", _S),
        ("err_min", _F),
        ("err_max", _F),
        ("unit_of_measure", _S),
        ("source", _S),
        ("n_steps", _I),
    ),
    # one row per unit and effect named (effect null: nothing named); the nested parts of a
    # finding (axes, estimate, stderr, units, evidence) are JSON text
    # one row per finding (calib_core.discovery.presentation.finding_rows): text cells already
    # in physical units; the unit's confounded groups, set-aside terms and advisor lines
    "discovery": _schema(
        *_KEYS,
        ("effect", _S),
        ("kind", _S),
        ("misfit", _B),
        ("unexplained", _B),
        ("run_id", _S),
        ("axes", _S),
        ("channels", _S),
        ("estimates", _S),
        ("evidence", _S),
        ("evidence_p", _F),
        ("heldout_rms_before", _F),
        ("heldout_rms_after", _F),
        ("gain", _F),
        ("separated_by", _S),
        ("confounded_groups", _S),
        ("partial_terms", _S),
        ("negligible_terms", _S),
        ("advice", _S),
    ),
    # the series behind each finding's figure (float32: figure data)
    "discovery_evidence": _schema(
        *_KEYS,
        ("effect", _S),
        ("kind", _S),
        ("channel", _S),
        ("rep", _I),
        ("step", _I),
        ("x", _F32),
        ("x_label", _S),
        ("x_unit", _S),
        ("y_unit", _S),
        ("before", _F32),
        ("fitted", _F32),
        ("after", _F32),
        ("run_id", _S),
    ),
    "navigation": _schema(*_KEYS, ("case", _S), ("t", _F), ("vel_err", _F), ("pos_err", _F)),
}


def conform(table: pa.Table, name: str) -> pa.Table:
    """``table`` with its table's declared schema: declared columns first, in order, cast to
    their type (missing ones all null); undeclared ones after them (a ``null``-typed one as
    string). The pandas metadata is kept (it restores the frame's extension dtypes)."""
    declared = TABLE_SCHEMAS[name]
    n = table.num_rows
    cols, fields = [], []
    untyped = set()  # columns that were Arrow null: their pandas metadata says "empty"
    for f in declared:
        if f.name in table.column_names:
            col = table.column(f.name)
            if not col.type.equals(f.type):
                if pa.types.is_null(col.type) or pa.types.is_list(f.type):
                    untyped.add(f.name)  # its pandas metadata describes the old type
                col = _cast(col, f.type)
        else:
            col = pa.nulls(n, f.type)
        cols.append(col)
        fields.append(f)
    for extra in table.schema:
        if extra.name in declared.names:
            continue
        col = table.column(extra.name)
        if pa.types.is_null(col.type):
            untyped.add(extra.name)
            col = col.cast(_S)
        cols.append(col)
        fields.append(pa.field(extra.name, col.type))
    return pa.Table.from_arrays(
        cols, schema=pa.schema(fields, metadata=_typed_metadata(table.schema.metadata, untyped, fields))
    )


def _cast(col: pa.ChunkedArray, t: pa.DataType) -> pa.ChunkedArray:
    """``col`` as type ``t``; a text column declared a list of texts (one warning written as
    a plain string) becomes one-element lists, an empty text an empty list."""
    if pa.types.is_list(t) and (pa.types.is_string(col.type) or pa.types.is_large_string(col.type)):
        return pa.chunked_array(
            [pa.array([None if v is None else ([v] if v else []) for v in col.to_pylist()], type=t)], type=t
        )
    return col.cast(t)


def _typed_metadata(metadata: dict | None, untyped: set[str], fields: list[pa.Field]) -> dict | None:
    """The pandas metadata with the columns that were all null described by their new
    type, so that they read back as a column of that type written by pandas would (object
    strings, float64), not as pandas' default for the Arrow type."""
    if not metadata or not untyped or b"pandas" not in metadata:
        return metadata
    doc = json.loads(metadata[b"pandas"])
    types = {f.name: f.type for f in fields}
    for c in doc.get("columns", []):
        t = types.get(c.get("name"))
        if c.get("name") not in untyped or t is None:
            continue
        if pa.types.is_floating(t):
            c["pandas_type"], c["numpy_type"] = "float64", "float64"
        elif pa.types.is_integer(t):
            c["pandas_type"], c["numpy_type"] = "int64", "int64"
        elif pa.types.is_boolean(t):
            c["pandas_type"], c["numpy_type"] = "bool", "object"
        elif pa.types.is_list(t):
            c["pandas_type"], c["numpy_type"] = "list[unicode]", "object"
        else:
            c["pandas_type"], c["numpy_type"] = "unicode", "object"
    return {**metadata, b"pandas": json.dumps(doc).encode()}


def schema_problem(schema: pa.Schema, name: str) -> str | None:
    """How a stored file's schema differs from the declared one (None: it conforms)."""
    declared = TABLE_SCHEMAS[name]
    for f in declared:
        if f.name not in schema.names:
            return f"column {f.name!r} is missing"
        got = schema.field(f.name).type
        if not got.equals(f.type):
            return f"column {f.name!r} has type {got}, declared {f.type}"
    return None


# the noise tables (docs/noise.md) are declared in their own module
from schemas.store_noise import NOISE_TABLE_SCHEMAS  # noqa: E402

TABLE_SCHEMAS.update(NOISE_TABLE_SCHEMAS)
