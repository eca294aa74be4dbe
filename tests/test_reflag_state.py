"""The re-flag after an update re-flags only the lots that can have changed (schemas.flagging's
flag state, cache/flag_state.parquet) and leaves the store exactly as a re-flag of every lot:
compared file by file with a store re-flagged in full, when the pooled scales stay, when they
move and another lot's flag changes, when a lot's files changed behind the state's back, and
without a state (stores of older code)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from flows import runtime

runtime.ensure_environment()

from calib_core.outliers import OutlierConfig, pooled_scales  # noqa: E402
from schemas import flagging  # noqa: E402
from schemas.results_store import ResultsStore  # noqa: E402

LOTS = ["L1", "L2", "L3"]
PARAMS = [("gyro", "k_g11"), ("gyro", "w0_x"), ("accel", "k_a11"), ("static", "scale_x")]
# the plain 3.5 rule: no threshold simulation in a unit test; lots of 8 units judged by
# their own lot (the fleet-history reference of small lots re-flags every lot, tested in
# tests/test_qa_small_lots.py)
CFG = OutlierConfig(family_alpha=0.0, history_units=0)
KEY = ("gyro", "k_g11")


def _base_summary(seed: int = 11, units_per_lot: int = 8) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    rows = []
    for lot in LOTS:
        for u in range(units_per_lot):
            for model, p in PARAMS:
                rows.append(
                    {
                        "lot": lot,
                        "unit": f"{lot}-U{u}",
                        "model": model,
                        "parameter": p,
                        "mean": rng.normal(),
                        "std": 0.1 * (1 + rng.random()),
                        "min": -1.0,
                        "max": 1.0,
                        "n_reps": 5,
                        "unit_of_measure": "",
                        "flagged": False,
                        "flag_reason": "",
                        "stale": False,
                        "stale_reason": "",
                        "run_id": "r0",
                    }
                )
    return pd.DataFrame(rows)


def _units(summary: pd.DataFrame) -> pd.DataFrame:
    u = summary[["lot", "unit"]].drop_duplicates().reset_index(drop=True)
    return u.assign(
        state="calibrated",
        reason="",
        n_sessions=5,
        n_ok=5,
        n_warned=0,
        n_failed=0,
        calibration_file="x.json",
        calibrated_at="t0",
        run_id="r0",
        updated_at="t0",
    )


def _rows(summary: pd.DataFrame, lot: str, unit: str | None = None) -> np.ndarray:
    m = (summary["lot"] == lot) & (summary["model"] == KEY[0]) & (summary["parameter"] == KEY[1])
    if unit is not None:
        m &= summary["unit"] == unit
    return np.flatnonzero(m.to_numpy())


def _store(root, summary: pd.DataFrame) -> ResultsStore:
    """A store as a nightly run of every lot leaves it (flags and flag state written)."""
    store = ResultsStore(root)
    store.write("summary", summary)
    store.write("units", _units(summary))
    flagging.reflag_after_update(store, LOTS, CFG)
    assert store.flag_state_path.exists()
    return store


def _update(store: ResultsStore, summary: pd.DataFrame, lot: str, unit: str) -> None:
    """What store_results does for a rerun of ``unit``: its summary and units rows replaced
    (flags cleared, scores missing)."""
    rows = summary[(summary["lot"] == lot) & (summary["unit"] == unit)]
    store.replace_units("summary", rows.assign(run_id="r1"), {(lot, unit)})
    store.replace_units("units", _units(rows).assign(run_id="r1"), {(lot, unit)})


def _files(store: ResultsStore) -> dict[str, bytes]:
    return {
        f"{name}/{p.name}": p.read_bytes()
        for name in ("summary", "units")
        for p in store.partitions(name).values()
    }


class _FullReflags:
    """Counts the re-flags of every lot (the path without a usable state)."""

    def __init__(self, monkeypatch):
        self.calls = 0
        full = flagging._reflag

        def spy(*args, **kwargs):
            self.calls += 1
            return full(*args, **kwargs)

        monkeypatch.setattr(flagging, "_reflag", spy)


def _rerun_both(
    tmp_path, base: pd.DataFrame, changed: pd.DataFrame, lot: str, unit: str, monkeypatch, before_update=None
):
    """The same update in two equal stores; re-flagged with the state in one and in full
    (state removed) in the other. Returns (partial result, full result, spy of the partial,
    the two stores)."""
    fast, full = _store(tmp_path / "fast", base), _store(tmp_path / "full", base)
    for store in (fast, full):
        if before_update is not None:
            before_update(store)
        _update(store, changed, lot, unit)
    full.flag_state_path.unlink()
    spy = _FullReflags(monkeypatch)
    got = flagging.reflag_after_update(fast, [lot], CFG)
    calls = spy.calls
    want = flagging.reflag_after_update(full, [lot], CFG)
    assert spy.calls == calls + 1  # the store without a state was re-flagged in full
    spy.calls = calls
    return got, want, spy, fast, full


def _same(got, want, fast: ResultsStore, full: ResultsStore) -> None:
    assert [x.to_dict() for x in got[0]] == [x.to_dict() for x in want[0]]
    assert got[1] == want[1]
    assert _files(fast) == _files(full)  # byte for byte, every lot of both tables
    # and the state left behind describes the store: the next re-flag re-flags nothing else
    assert flagging._lot_files(fast) == fast.read_flag_state()[1]["files"]


def test_scales_unchanged_only_the_touched_lot_is_reflagged(tmp_path, monkeypatch):
    base = _base_summary()
    changed = base.copy()
    i = _rows(base, "L1")
    x = base.loc[i, "mean"].to_numpy()
    dev = x - np.median(x)
    far = i[np.argmax(np.abs(dev))]
    unit = str(base.loc[far, "unit"])
    # the value farthest from the lot median moved farther out: the lot median and the
    # pooled scale stay
    changed.loc[far, "mean"] += 10.0 * np.sign(dev.max() if dev.max() > -dev.min() else dev.min())
    assert pooled_scales(changed, CFG) == pooled_scales(base, CFG)
    got, want, spy, fast, full = _rerun_both(tmp_path, base, changed, "L1", unit, monkeypatch)
    assert spy.calls == 0  # the partial path
    _same(got, want, fast, full)
    flagged = fast.read("units")
    assert flagged.loc[flagged["unit"] == unit, "flagged"].item()  # the new flag is there
    assert got[1] == ["L1"]


def test_scales_move_and_another_lot_flag_changes(tmp_path, monkeypatch):
    base = _base_summary()
    # L1's change: the unit at the lot median moves out, which moves L1's median and the
    # pooled scale of k_g11
    i1 = _rows(base, "L1")
    mid = i1[np.argsort(base.loc[i1, "mean"].to_numpy())[3]]
    unit = str(base.loc[mid, "unit"])
    shift = base.loc[i1, "mean"].max() + 3.0 - base.loc[mid, "mean"]

    def moved(s: pd.DataFrame) -> pd.DataFrame:
        s = s.copy()
        s.loc[mid, "mean"] += shift
        return s

    s0, s1 = pooled_scales(base, CFG)[KEY][0], pooled_scales(moved(base), CFG)[KEY][0]
    assert s0 != s1
    # L2's largest unit placed between the thresholds of the two scales: it stays L2's
    # largest value and above the pooled median, so neither scale depends on it
    i2 = _rows(base, "L2")
    top = i2[np.argmax(base.loc[i2, "mean"].to_numpy())]
    med2 = float(np.median(base.loc[i2, "mean"]))
    base.loc[top, "mean"] = med2 + 3.5 * (s0 + s1) / 2
    changed = moved(base)
    assert pooled_scales(base, CFG)[KEY][0] == s0 and pooled_scales(changed, CFG)[KEY][0] == s1
    z0, z1 = (base.loc[top, "mean"] - med2) / s0, (base.loc[top, "mean"] - med2) / s1
    assert (abs(z0) > 3.5) != (abs(z1) > 3.5)
    top_unit = str(base.loc[top, "unit"])
    got, want, spy, fast, full = _rerun_both(tmp_path, base, changed, "L1", unit, monkeypatch)
    assert spy.calls == 1  # the scales moved: every lot re-flagged
    _same(got, want, fast, full)
    assert "L2" in got[1]  # L2's flagged unit changed: its report is rebuilt
    units = fast.read("units")
    assert bool(units.loc[units["unit"] == top_unit, "flagged"].item()) == (abs(z1) > 3.5)


def test_a_lot_rewritten_behind_the_state_is_reflagged(tmp_path, monkeypatch):
    base = _base_summary()

    def spoil_l3_flags(store: ResultsStore) -> None:  # e.g. a lot report under another config
        s = store.read("summary", lots=["L3"])
        store.write("summary", s.assign(score=0.5, flagged=True), lots=["L3"])
        u = store.read("units", lots=["L3"])
        store.write("units", u.assign(flagged=True, flag_reason="?"), lots=["L3"])

    got, want, spy, fast, full = _rerun_both(
        tmp_path, base, base, "L1", "L1-U0", monkeypatch, before_update=spoil_l3_flags
    )
    assert spy.calls == 0
    _same(got, want, fast, full)
    assert "L3" in got[1]  # its flagged units were restored


@pytest.mark.parametrize("damage", ["missing", "broken", "other config"])
def test_without_a_usable_state_every_lot_is_reflagged(tmp_path, monkeypatch, damage):
    base = _base_summary()
    store = _store(tmp_path, base)
    if damage == "missing":  # a store of the older code
        store.flag_state_path.unlink()
    elif damage == "broken":
        store.flag_state_path.write_bytes(b"not parquet")
    cfg = (
        OutlierConfig(family_alpha=0.0, z_threshold=3.0, history_units=0) if damage == "other config" else CFG
    )
    spy = _FullReflags(monkeypatch)
    flagging.reflag_after_update(store, ["L1"], cfg)
    assert spy.calls == 1
    flagging.reflag_after_update(store, ["L1"], cfg)  # the state is back
    assert spy.calls == 1
