"""Every table directory of the results store reads as one table with pandas, pyarrow.dataset
and DuckDB's glob, whether the table has rows or not: a table without rows keeps an
``empty.parquet`` with its declared schema, removed once it has a lot file."""

from __future__ import annotations

import duckdb  # a test dependency (pyproject.toml), for this check only
import pandas as pd
import pyarrow.dataset as ds

from schemas.results_store import EMPTY_FILE, TABLES, ResultsStore
from schemas.store_tables import TABLE_SCHEMAS


def read_three_ways(d) -> list[tuple[str, int, list[str]]]:
    """(reader, rows, columns) of the directory ``d`` through each reader."""
    out = [("pandas", *_shape(pd.read_parquet(d)))]
    t = ds.dataset(d, format="parquet").to_table()
    out.append(("pyarrow.dataset", t.num_rows, t.column_names))
    rel = duckdb.sql(f"select * from read_parquet('{d}/*.parquet')")
    out.append(("duckdb", len(rel.fetchall()), rel.columns))
    return out


def _shape(df: pd.DataFrame) -> tuple[int, list[str]]:
    return len(df), list(df.columns)


def test_every_table_reads_empty_then_with_rows_then_empty_again(tmp_path):
    store = ResultsStore(tmp_path)
    for name in TABLES:
        store.write(name, pd.DataFrame())
        d = store.table_dir(name)
        assert [p.name for p in d.iterdir()] == [EMPTY_FILE], name
        for reader, rows, cols in read_three_ways(d):
            assert rows == 0 and cols[: len(TABLE_SCHEMAS[name])] == TABLE_SCHEMAS[name].names, (name, reader)
        assert store.partitions(name) == {} and not len(store.read(name))
    assert store.verify() == []

    rows = pd.DataFrame(
        {"lot": ["L1", "L2"], "unit": ["U1", "U2"], "effect": ["lever_arm"] * 2, "channel": ["ax"] * 2}
    )
    store.write("discovery_evidence", rows)
    d = store.table_dir("discovery_evidence")
    assert not (d / EMPTY_FILE).exists() and len(store.partitions("discovery_evidence")) == 2
    for reader, n, _ in read_three_ways(d):
        assert n == 2, reader
    store.write("discovery_evidence", rows.iloc[0:0])  # every lot loses its rows
    assert [p.name for p in d.iterdir()] == [EMPTY_FILE]
    for reader, n, _ in read_three_ways(d):
        assert n == 0, reader


def test_duckdb_counts_no_row_in_an_empty_table(tmp_path):
    store = ResultsStore(tmp_path)
    store.write("discovery_evidence", pd.DataFrame())
    n = duckdb.sql(f"select count(*) from read_parquet('{store.table_dir('discovery_evidence')}/*.parquet')")
    assert n.fetchall() == [(0,)]
