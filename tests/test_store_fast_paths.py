"""The store's fast paths (docs/benchmarks.md): the JSON layout written with the C encoder,
and ``replace_units`` merging a lot file in Arrow. Expected values come from the plain
computations they replace: ``json.dumps(calib_core.results.to_jsonable(doc))`` and pandas
(concatenate, drop the replaced units, stable sort by the table's keys)."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from calib_core.results import to_jsonable
from schemas.calibration_file import dumps_json, write_json_atomic
from schemas.results_store import ResultsStore
from schemas.store_frames import normalise

KEYS = ["lot", "unit", "rep", "model", "parameter", "effect"]


# --- JSON -----------------------------------------------------------------------------------------
def random_doc(rng: np.random.Generator, depth: int = 0):
    """Nested dicts and lists of Python and numpy values, some non-finite."""
    kind = rng.integers(0, 9 if depth < 4 else 6)
    if kind == 0:
        return float(rng.normal()) if rng.uniform() > 0.1 else float(rng.choice([np.nan, np.inf, -np.inf]))
    if kind == 1:
        return int(rng.integers(-5, 5))
    if kind == 2:
        return str(rng.choice(["a", "NaN text", 'é"\\\n', "Infinity", ""]))
    if kind == 3:
        return rng.normal(size=(int(rng.integers(0, 3)), 3))  # ndarray, maybe a NaN below
    if kind == 4:
        return [np.float64(rng.normal()), np.int64(3), np.bool_(True), None, True]
    if kind == 5:
        return np.float32(rng.choice([1.5, np.nan]))
    if kind in (6, 7):
        return {f"k{i}": random_doc(rng, depth + 1) for i in range(int(rng.integers(0, 4)))}
    return [random_doc(rng, depth + 1) for _ in range(int(rng.integers(0, 4)))]


@pytest.mark.parametrize("seed", range(40))
def test_dumps_json_null_mode_equals_to_jsonable(seed):
    rng = np.random.default_rng(seed)
    doc = {f"top{i}": random_doc(rng) for i in range(5)}
    if rng.uniform() < 0.3:
        doc["arr"] = np.array([1.0, np.nan])
    want = json.loads(json.dumps(to_jsonable(doc), allow_nan=False))
    assert json.loads(dumps_json(doc, nonfinite="null")) == want


def test_dumps_json_strict_mode_refuses_non_finite_like_json():
    with pytest.raises(ValueError):
        dumps_json({"a": {"b": [1.0, float("nan")]}})
    with pytest.raises(ValueError):
        dumps_json({"a": np.array([np.inf])})
    with pytest.raises(TypeError):
        dumps_json({"a": object()})
    # a string that reads "NaN" is not a number
    assert json.loads(dumps_json({"a": ["NaN", "-Infinity"]})) == {"a": ["NaN", "-Infinity"]}


def test_dumps_json_layout_objects_one_key_per_line_matrices_on_one_line():
    doc = {
        "K_g": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        "units": {"K_g": "x"},
        "terms": [{"name": "t", "params": {"a": 1}}],
        "empty": {},
        "none": [],
    }
    text = dumps_json(doc)
    assert text == (
        "{\n"
        '  "K_g": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],\n'
        '  "units": {\n    "K_g": "x"\n  },\n'
        '  "terms": [\n    {\n      "name": "t",\n      "params": {\n        "a": 1\n      }\n'
        "    }\n  ],\n"
        '  "empty": {},\n'
        '  "none": []\n'
        "}\n"
    )
    assert json.loads(text) == json.loads(json.dumps(doc, indent=2))


def test_null_keys_convert_only_those_keys(tmp_path):
    doc = {"K_g": [[1.0]], "extra": {"x": float("nan")}}
    write_json_atomic(tmp_path / "a.json", doc, null_keys={"extra"})
    assert json.loads((tmp_path / "a.json").read_text()) == {"K_g": [[1.0]], "extra": {"x": None}}
    with pytest.raises(ValueError):
        write_json_atomic(tmp_path / "b.json", {"K_g": [[float("nan")]], "extra": {}}, null_keys={"extra"})
    assert not (tmp_path / "b.json").exists()


# --- replace_units ---------------------------------------------------------------------------------
def residual_rows(lot: str, units: list[str], seed: int, reps=(1, 2)) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    n = 5
    k = len(reps)
    return pd.DataFrame(
        {
            "lot": [lot] * (len(units) * k * n),
            "unit": np.repeat(units, k * n),
            "rep": np.tile(np.repeat(list(reps), n), len(units)),
            "step": np.tile(np.arange(n), k * len(units)),
            "channel": rng.choice(["gx", "ax"], size=len(units) * k * n),
            "residual": rng.normal(size=len(units) * k * n),
        }
    )


def expected_after(
    before: pd.DataFrame, new: pd.DataFrame | None, units: set, name: str = "residuals"
) -> pd.DataFrame:
    keys = pd.Series(list(zip(before["lot"].astype(object), before["unit"].astype(object))))
    parts = [before[~keys.isin(units).to_numpy()]] + ([new] if new is not None else [])
    df = normalise(pd.concat(parts, ignore_index=True), name)
    return df.sort_values([c for c in KEYS if c in df], kind="stable").reset_index(drop=True)


UNITS = [f"U{i:03d}" for i in (3, 1, 7, 5, 9, 2)]


@pytest.mark.parametrize(
    "case", ["middle", "first", "last", "new unit", "two apart", "remove only", "all units"]
)
def test_replace_units_merge_equals_pandas(tmp_path, case):
    st = ResultsStore(tmp_path)
    before = pd.concat([residual_rows("L1", UNITS, 1), residual_rows("L2", UNITS[:2], 2)], ignore_index=True)
    st.write("residuals", before)
    units = {
        "middle": ["U005"],
        "first": ["U001"],
        "last": ["U009"],
        "new unit": ["U004"],
        "two apart": ["U002", "U009"],
        "remove only": ["U003"],
        "all units": UNITS,
    }[case]
    new = None if case == "remove only" else residual_rows("L1", units, 7, reps=(3, 1))
    keys = {("L1", u) for u in units}
    st.replace_units("residuals", new, keys)
    got = st.read("residuals")
    pd.testing.assert_frame_equal(got, expected_after(st_read_all(before), new, keys), check_exact=True)
    # the other lot's file was not rewritten, and a second pass changes nothing
    st.replace_units("residuals", new, keys)
    pd.testing.assert_frame_equal(st.read("residuals"), got, check_exact=True)


def st_read_all(df: pd.DataFrame) -> pd.DataFrame:
    df = normalise(df, "residuals")
    return df.sort_values([c for c in KEYS if c in df], kind="stable").reset_index(drop=True)


def test_replace_units_other_types_fall_back_to_pandas(tmp_path):
    """New rows whose column types differ from the stored ones (a column all missing)."""
    st = ResultsStore(tmp_path)
    before = residual_rows("L1", UNITS, 1)
    st.write("residuals", before)
    new = residual_rows("L1", ["U005"], 3)
    new["channel"] = None
    st.replace_units("residuals", new, {("L1", "U005")})
    want = expected_after(st_read_all(before), new, {("L1", "U005")})
    pd.testing.assert_frame_equal(st.read("residuals"), want, check_exact=True, check_dtype=False)


def test_replace_units_set_values_marks_kept_rows_in_one_write(tmp_path):
    st = ResultsStore(tmp_path)
    rows = []
    for u in ("U1", "U2", "U3"):
        rows.append(
            {
                "lot": "L1",
                "unit": u,
                "model": "gyro",
                "parameter": "k",
                "mean": 1.0,
                "stale": False,
                "stale_reason": "",
                "run_id": "r1",
            }
        )
    st.write("summary", pd.DataFrame(rows))
    new = pd.DataFrame([{**rows[0], "mean": 2.0, "run_id": "r2"}])
    st.replace_units(
        "summary", new, {("L1", "U1")}, set_values={("L1", "U2"): {"stale": True, "stale_reason": "failed"}}
    )
    got = st.read("summary").set_index("unit")
    assert got.loc["U1", "mean"] == 2.0 and got.loc["U1", "run_id"] == "r2"
    assert bool(got.loc["U2", "stale"]) and got.loc["U2", "stale_reason"] == "failed"
    assert not bool(got.loc["U3", "stale"]) and got.loc["U3", "stale_reason"] == ""
