"""The results store's noise tables: each unit's measured noise model and its Allan curves.

- ``noise``: one row per unit, channel and coefficient (``quantization``, ``white``,
  ``bias_instability``, ``random_walk``, ``ramp``, and one ``periodic`` row per line named,
  ``frequency_hz`` set), with its value, 95 % interval (``lo``, ``hi``) and unit. A
  coefficient the recording cannot determine has a null value and its ``reason``. The lot's
  judgement is on each row: ``flagged``, ``flag_reason``, ``score`` (robust z of log10 of
  the value against the lot), ``lot_median``.
- ``noise_allan``: the Allan deviation of each unit and channel at each cluster time, with
  its interval and the fitted model's (what the lot report overlays).

``schemas.store_tables`` registers both (its TABLE_SCHEMAS), so the store writes them lot by
lot like every table, and each reads as one table in pandas, pyarrow.dataset and DuckDB.
The rows come from :mod:`calib_core.noise_fleet`; :func:`noise_store_rows` and
:func:`write_noise_tables` are the unit pipeline's and the store's sides.
"""

from __future__ import annotations

from typing import Any

import pandas as pd
import pyarrow as pa

_S, _I, _F, _B = pa.large_string(), pa.int64(), pa.float64(), pa.bool_()

NOISE_TABLE_SCHEMAS: dict[str, pa.Schema] = {
    "noise": pa.schema(
        [
            ("lot", _S),
            ("unit", _S),
            ("channel", _S),
            ("coefficient", _S),
            ("value", _F),
            ("lo", _F),
            ("hi", _F),
            ("unit_of_measure", _S),
            ("frequency_hz", _F),
            ("reason", _S),
            ("source", _S),
            ("duration_s", _F),
            ("rate_hz", _F),
            ("flagged", _B),
            ("flag_reason", _S),
            ("score", _F),
            ("lot_median", _F),
            ("run_id", _S),
        ]
    ),
    "noise_allan": pa.schema(
        [
            ("lot", _S),
            ("unit", _S),
            ("channel", _S),
            ("tau_s", _F),
            ("adev", _F),
            ("adev_lo", _F),
            ("adev_hi", _F),
            ("fit_adev", _F),
            ("unit_of_measure", _S),
            ("source", _S),
            ("run_id", _S),
        ]
    ),
}
NOISE_TABLES = tuple(NOISE_TABLE_SCHEMAS)


def write_noise_tables(store: Any, results: list, run_id: str) -> None:
    """The noise rows of the units ``results`` (``flows.unit_pipeline.UnitResult`` with a
    ``noise`` attribute: :class:`calib_core.noise_fleet.UnitNoise` or None) replace those
    units' rows; a unit measured without any noise data loses its rows."""
    units = {(ur.lot, ur.unit) for ur in results if getattr(ur, "calibrated", False)}
    if not units:
        return
    noise, allan = [], []
    for ur in results:
        un = getattr(getattr(ur, "outcome", None), "noise", None)
        if un is None or (ur.lot, ur.unit) not in units:
            continue
        noise += [{**r, "lot": ur.lot, "unit": ur.unit, "run_id": run_id} for r in un.coefficient_rows]
        allan += [{**r, "lot": ur.lot, "unit": ur.unit, "run_id": run_id} for r in un.allan_rows]
    store.replace_units("noise", pd.DataFrame(noise) if noise else None, units)
    store.replace_units("noise_allan", pd.DataFrame(allan) if allan else None, units)


def flag_noise(store: Any, lot_flags: list, config: Any, thresholds: Any) -> None:
    """Judge the noise rows of the lots ``lot_flags`` (``calib_core.outliers.LotFlags``) by
    :func:`calib_core.noise_fleet.judge_noise`: the flags join each lot's flags (so the unit
    is flagged with its reason in the units table and its calibration file's QA status) and
    the rows' flag columns are written back."""
    from calib_core.noise_fleet import judge_noise

    if not lot_flags or not store.has_table("noise"):
        return
    by_lot = {lf.lot: lf for lf in lot_flags}
    rows = store.read("noise", lots=list(by_lot))
    if not len(rows):
        return
    judged = []
    for lot, part in rows.groupby(rows["lot"].astype(str), sort=True):
        new, flags, note = judge_noise(
            part, config.limits, thresholds, config.z_threshold, config.family_alpha, config.min_units
        )
        judged.append(new)
        lf = by_lot[lot]
        lf.flags.extend(flags)
        if note:
            lf.note = f"{lf.note}; noise: {note}" if lf.note else f"noise: {note}"
    store.write(
        "noise", pd.concat(judged, ignore_index=True), lots=list(by_lot), skip_unchanged=True, previous=rows
    )
