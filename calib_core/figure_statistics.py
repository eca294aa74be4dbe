"""The reductions behind the reports' figures, computed from stored rows when a report is
built: the per-step residual envelope over a unit's repetitions, the RMS residual per unit,
sensor and model, Table 3's min..max over the repetitions, a unit's parameter changes over
its calibrations, and the fleet index's lot trend of each key element over the units'
current calibration files. The reports only draw and format what these return; the lot
statistics of the key-parameter tables are the summary's own columns (written by the
re-flag, :data:`calib_core.outliers.LOT_COLUMNS`).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from calib_core.outliers import MIN_UNITS_FOR_SCATTER, robust_scale


def residual_envelope(res: pd.DataFrame | None) -> pd.DataFrame | None:
    """Per unit, model, test, step and channel of the ``residuals`` rows: the mean residual
    over the repetitions (``residual``), its min..max envelope (``rmin``, ``rmax``), the
    number of repetitions (``n``) and the step's rate, angle and up axis. This is the
    downsampling of the residual traces (a factor n_reps) that keeps the repetition spread
    visible as error bars."""
    if res is None or not len(res):
        return None
    res = res.copy()
    if "model" not in res.columns:
        res["model"] = "baseline"
    for c, d in (("rate_dps", 0.0), ("angle_deg", 0.0), ("up_axis", ""), ("test", "")):
        if c not in res.columns:
            res[c] = d
    keys = ["unit", "model", "test", "step", "channel"]
    g = res.groupby(keys, sort=True, dropna=False)
    return g.agg(
        residual=("residual", "mean"),
        rmin=("residual", "min"),
        rmax=("residual", "max"),
        rate_dps=("rate_dps", "first"),
        angle_deg=("angle_deg", "first"),
        up_axis=("up_axis", "first"),
        n=("residual", "size"),
    ).reset_index()


def compensation_envelope(compensation: pd.DataFrame) -> pd.DataFrame:
    """xu2016 Table 3 over a unit's repetitions: per unit, input axis, method and output
    axis of the ``compensation`` rows, the smallest ``err_min`` (``lo``), the largest
    ``err_max`` (``hi``) and the number of repetitions (``n_reps``)."""
    return compensation.groupby(["unit", "input_axis", "method", "output_axis"], sort=True).agg(
        lo=("err_min", "min"), hi=("err_max", "max"), n_reps=("rep", "nunique")
    )


def changes_since_first(values: pd.DataFrame) -> pd.DataFrame:
    """Each column of ``values`` (rows in time order) minus its first row: a unit's key
    parameters as the change since its first calibration."""
    return values - values.iloc[0]


def residual_rms(envelope: pd.DataFrame | None) -> pd.DataFrame | None:
    """RMS of the mean step residuals (:func:`residual_envelope`) per unit, sensor (``gyro``:
    channels g*, deg/s; ``accel``: a*, g) and model: columns unit, sensor, model, rms."""
    if envelope is None or not len(envelope):
        return None
    a = envelope.assign(
        sensor=np.where(envelope["channel"].astype(str).str.startswith("g"), "gyro", "accel"),
        sq=envelope["residual"].astype(float) ** 2,
    )
    rms = a.groupby(["unit", "sensor", "model"])["sq"].mean() ** 0.5
    return rms.rename("rms").reset_index()


def lot_trends(history: pd.DataFrame, names: list[str]) -> pd.DataFrame:
    """Per lot: the median over its units of each element of ``names`` and its scatter (the
    lot scatter of the summary: :func:`calib_core.outliers.robust_scale` of the units'
    values, from MIN_UNITS_FOR_SCATTER units; column ``<name>_spread``), from each unit's
    current calibration (its last ``produced`` row of ``history``), placed at the lot's
    acquisition time (the median of its units' ``time``). A rerun of one unit replaces that
    unit's value in its lot's median; it never makes a point of its own."""
    if not len(history):
        return pd.DataFrame()
    cur = (
        history.sort_values("produced", kind="stable")
        .groupby(["lot", "unit"], sort=False, dropna=False)
        .tail(1)
    )
    rows = []
    for lot, g in cur.groupby("lot", sort=False, dropna=False):
        t = g["time"].sort_values()
        row = {
            "lot": lot,
            "time": t.iloc[(len(t) - 1) // 2],
            "n_units": g["unit"].nunique(),
            "time_source": ", ".join(sorted(set(g["time_source"].astype(str)))),
        }
        values = g[names].to_numpy(float)  # one block per group, not a column at a time
        for k, n in enumerate(names):
            v = values[:, k]
            v = v[np.isfinite(v)]
            row[n] = float(np.median(v)) if len(v) else np.nan
            row[n + "_spread"] = robust_scale(v) if len(v) >= MIN_UNITS_FOR_SCATTER else np.nan
        rows.append(row)
    return pd.DataFrame(rows).sort_values("time", kind="stable").reset_index(drop=True)
