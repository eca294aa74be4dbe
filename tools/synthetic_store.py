"""A synthetic results store for report tests, benchmarks and screenshots.

Builds, with pandas and a seeded generator, the tables the nightly flow writes under
``--results`` (columns as in docs/reports.md): a lot of ``n_units`` units with
``n_reps`` repetitions each, a few outlier units whose parameters are shifted far outside
the lot and flagged in ``summary.parquet``, and failed sessions. Values follow the orders
of magnitude of xu2016 Tables 1-3 (deg/s, g). It is not a calibration: no raw data and no
fit are involved, only the store layout, so reports can be exercised without the pipeline.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pandas as pd

from calib_core.outliers import lot_statistics
from calib_core.results import stderr_of_mean
from schemas.results_store import TABLE_COLUMNS, TIMESTAMP_FORMAT, ResultsStore, write_parquet_atomic

AXES = "xyz"
CHANNELS = ("gx", "gy", "gz", "ax", "ay", "az")

# xu2016 Table 1 / Table 2 averages: the lot centre of the synthetic units.
KG_CENTRE = np.array(
    [[0.99972, -0.01199, -0.00059], [0.02394, 1.00046, 0.01053], [0.01087, 0.01490, 1.00579]]
)
KA_CENTRE = np.array(
    [[0.96667, 0.01434, -0.00180], [-0.01760, 0.96965, -0.00851], [0.01476, -0.01494, 0.99326]]
)
W0_CENTRE = np.array([-0.25, -0.71, -2.01])  # deg/s
F0_CENTRE = np.array([-0.0016, 0.0011, 0.0027])  # g
RATES_DPS = (6, 12, 24, 30, 60, 120, 180, 240, 300)


@dataclass
class SyntheticLot:
    """What was generated, so tests can compare the report against the truth."""

    root: Path
    lot: str
    units: list[str]
    outliers: dict[str, list[tuple[str, str]]]  # unit -> [(model, parameter)]
    failed: list[tuple[str, int]]  # (unit, rep)
    warned: list[tuple[str, int]]
    run_ids: list[str] = field(default_factory=list)


def _unit_truth(rng: np.random.Generator) -> dict[str, tuple[list[str], np.ndarray, np.ndarray, str]]:
    """Per-model (names, unit-level values, repetition scatter, unit of measure)."""
    kg = KG_CENTRE + rng.normal(0, 4e-4, (3, 3))
    ka = KA_CENTRE + rng.normal(0, 6e-4, (3, 3))
    w0 = W0_CENTRE + rng.normal(0, 0.08, 3)
    f0 = F0_CENTRE + rng.normal(0, 4e-4, 3)
    mat = [f"{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3)]
    static_names = (
        [f"b_{a}" for a in AXES] + [f"s_{a}" for a in AXES] + [f"theta_{a}{b}" for a in AXES for b in AXES]
    )
    static_vals = np.concatenate(
        [f0 + rng.normal(0, 1e-4, 3), np.diag(ka) + rng.normal(0, 2e-4, 3), rng.normal(0, 0.4, 9)]
    )
    lever = np.array([6.0, 0.0, 0.0, 0.0, 6.0, 0.0, 0.0, 0.0, 6.0]) + rng.normal(0, 0.3, 9)
    return {
        "gyro": (
            [f"k_g{m}" for m in mat] + [f"w0_{a}" for a in AXES],
            np.concatenate([kg.ravel(), w0]),
            np.r_[np.full(9, 3e-5), np.full(3, 0.012)],
            "deg/s per deg/s|deg/s",
        ),
        "accel": (
            [f"k_a{m}" for m in mat] + [f"f0_{a}" for a in AXES],
            np.concatenate([ka.ravel(), f0]),
            np.r_[np.full(9, 2e-4), np.full(3, 5e-5)],
            "g per g|g",
        ),
        "gyro_traditional": (
            [f"s_g{m}" for m in mat] + [f"b_g{a}" for a in AXES],
            np.concatenate([np.linalg.inv(kg).ravel(), -np.linalg.inv(kg) @ w0]),
            np.r_[np.full(9, 3e-5), np.full(3, 0.012)],
            "deg/s per deg/s|deg/s",
        ),
        "accel_static": (
            static_names,
            static_vals,
            np.r_[np.full(3, 5e-5), np.full(3, 2e-4), np.full(9, 0.02)],
            "g|1|deg",
        ),
        "lever_arm": ([f"r{i}{a}" for i in (1, 2, 3) for a in AXES], lever, np.full(9, 0.15), "mm"),
    }


def _units_of(model: str, names: list[str], spec: str) -> list[str]:
    parts = spec.split("|")
    if model in ("gyro", "accel", "gyro_traditional"):
        return [parts[0]] * 9 + [parts[1]] * 3
    if model == "accel_static":
        return [parts[0]] * 3 + [parts[1]] * 3 + [parts[2]] * 9
    return [parts[0]] * len(names)


# Outlier injections: (model, parameter, shift in units of that parameter).
OUTLIER_SHIFTS = [
    [("gyro", "k_g11", 0.012), ("gyro", "w0_z", 1.5)],
    [("accel", "k_a22", -0.02), ("accel", "f0_x", 0.012)],
]


def build_synthetic_store(
    root: str | Path,
    lot: str = "LOT-2026-11A",
    n_units: int = 12,
    n_reps: int = 5,
    n_outliers: int = 2,
    n_failed: int = 1,
    n_runs: int = 3,
    seed: int = 20261121,
    discovery: bool = True,
    navigation: bool = True,
    nav_samples: int = 3000,
    code_version: str = "0.1.0+g94590e6",
    unit_prefix: str = "U",
) -> SyntheticLot:
    """Write a synthetic results store for one lot under ``root`` and return its truth."""
    rng = np.random.default_rng(seed)
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    units = [f"{unit_prefix}{i:03d}" for i in range(1, n_units + 1)]
    outlier_units = (
        [units[i] for i in np.linspace(2, n_units - 3, n_outliers).astype(int)] if n_outliers else []
    )
    failed_units = [u for u in units if u not in outlier_units][1 : 1 + n_failed]
    failed = [(u, 3) for u in failed_units]
    warned = [(units[-1], 2)]
    t_run = datetime(2026, 11, 21, 2, 0, tzinfo=UTC)
    run_ids = [f"run-{(t_run - timedelta(days=d)):%Y%m%dT%H%M%SZ}" for d in range(n_runs - 1, -1, -1)]
    run_id = run_ids[-1]

    sessions, params, resid, comp, disc, nav = [], [], [], [], [], []
    truths: dict[str, dict] = {}
    outliers: dict[str, list[tuple[str, str]]] = {}
    for ui, unit in enumerate(units):
        truth = _unit_truth(rng)
        if unit in outlier_units:
            shifts = OUTLIER_SHIFTS[outlier_units.index(unit) % len(OUTLIER_SHIFTS)]
            outliers[unit] = [(m, p) for m, p, _ in shifts]
            for model, pname, shift in shifts:
                names, vals, sc, spec = truth[model]
                vals = vals.copy()
                vals[names.index(pname)] += shift
                truth[model] = (names, vals, sc, spec)
        truths[unit] = truth
        for rep in range(1, n_reps + 1):
            status, code, msg, warn = "ok", "", "", ""
            if (unit, rep) in failed:
                status, code = "failed", "E_MISSING_COLUMN"
                msg = f"lot={lot}/unit={unit}/rep={rep}: samples.parquet: required column 'gz' is missing"
            elif (unit, rep) in warned:
                status, warn = "warned", "W_SATURATION: 3 of 118 steps near the gyro range, dropped"
            when = t_run + timedelta(minutes=2 * ui + rep * 0.3)
            sessions.append(
                dict(
                    lot=lot,
                    unit=unit,
                    rep=rep,
                    status=status,
                    error_code=code,
                    message=msg,
                    warnings=warn,
                    fingerprint=f"{rng.integers(2**63):016x}",
                    run_id=run_id,
                    path=f"lot={lot}/unit={unit}/rep={rep}",
                    calibrated_at=when.isoformat(),
                )
            )
            if status == "failed":
                continue
            for model, (names, vals, sc, spec) in truth.items():
                rep_vals = vals + rng.normal(0, sc)
                for n, v, s, uom in zip(names, rep_vals, sc * 0.4, _units_of(model, names, spec)):
                    params.append(
                        dict(
                            lot=lot,
                            unit=unit,
                            rep=rep,
                            model=model,
                            parameter=n,
                            value=v,
                            stderr=s,
                            unit_of_measure=uom,
                            code_version=code_version,
                            run_id=run_id,
                        )
                    )
            bad = unit in outlier_units
            resid.extend(_residual_rows(rng, lot, unit, rep, bad))
            comp.extend(_compensation_rows(rng, lot, unit, rep))
        if discovery:
            disc.extend(_discovery_rows(rng, lot, unit, unit in outlier_units))
        if navigation:
            nav.extend(_navigation_rows(rng, lot, unit, nav_samples))

    sessions_df = pd.DataFrame(sessions)
    params_df = pd.DataFrame(params)
    summary_df = _summary(params_df, outliers)
    _write(root / "sessions.parquet", sessions_df)
    _write(root / "parameters.parquet", params_df)
    _write(root / "summary.parquet", summary_df)
    _write(root / "units.parquet", _units_table(sessions_df, lot, run_id))
    _write(root / "residuals.parquet", pd.DataFrame(resid))
    _write(root / "compensation.parquet", pd.DataFrame(comp))
    if discovery:
        _write(root / "discovery.parquet", pd.DataFrame(disc))
    if navigation:
        _write(root / "navigation.parquet", pd.concat(nav, ignore_index=True))
    _write_history(root, lot, units, truths, run_ids, rng, code_version)
    for i, rid in enumerate(run_ids):
        when = t_run - timedelta(days=n_runs - 1 - i)
        doc = dict(
            run_id=rid,
            started_at=when.isoformat(),
            finished_at=(when + timedelta(minutes=31)).isoformat(),
            code_version=code_version,
            lots=[lot],
            kind="nightly",
        )
        (root / "runs").mkdir(exist_ok=True)
        path = root / "runs" / f"{rid}.json"
        if path.exists():  # several lots calibrated by the same run
            doc["lots"] = sorted(set(json.loads(path.read_text()).get("lots", [])) | {lot})
        path.write_text(json.dumps(doc, indent=2))
    return SyntheticLot(root, lot, units, outliers, failed, warned, run_ids)


def _write(path: Path, df: pd.DataFrame) -> None:
    """Through the results store's own writer (its column order and key dtypes); tables it
    does not know (navigation) as plain atomic Parquet. Several lots append, as flows do."""
    store = ResultsStore(path.parent)
    name = path.stem
    if name in TABLE_COLUMNS:
        old = store.read(name) if store.has_table(name) else None
        store.write(name, df if old is None else pd.concat([old, df], ignore_index=True))
    else:
        if path.exists():
            df = pd.concat([pd.read_parquet(path), df], ignore_index=True)
        write_parquet_atomic(df, path)


def _summary(params: pd.DataFrame, outliers: dict[str, list[tuple[str, str]]]) -> pd.DataFrame:
    """The summary rows of the synthetic parameters, each statistic by the definition the
    pipeline stores (calib_core.results.stderr_of_mean, calib_core.outliers.lot_statistics);
    the flags placed by hand (``outliers``)."""
    g = params.groupby(["lot", "unit", "model", "parameter"], sort=False)
    s = g["value"].agg(["mean", "std", "min", "max", "count"]).reset_index()
    s = s.rename(columns={"count": "n_reps"})
    s["stderr_of_mean"] = [stderr_of_mean(se.to_numpy(float)[:, None])[0] for _, se in g["stderr"]]
    s["unit_of_measure"] = g["unit_of_measure"].first().to_numpy()
    for col in ("lot_median", "lot_scatter", "lot_median_std"):
        s[col] = np.nan
    for _, pos in s.groupby(["lot", "model", "parameter"], sort=False).indices.items():
        stats = lot_statistics(
            s["mean"].to_numpy()[pos], s["std"].to_numpy()[pos], s["n_reps"].to_numpy()[pos]
        )
        s.loc[s.index[pos], ["lot_median", "lot_scatter", "lot_median_std"]] = stats
    s["score"] = (s["mean"] - s["lot_median"]) / s["lot_scatter"].where(s["lot_scatter"] > 0)
    s["flagged"] = False
    s["flag_reason"] = ""
    s["stale"] = False
    s["stale_reason"] = ""
    for unit, pairs in outliers.items():
        for model, pname in pairs:
            m = (s.unit == unit) & (s.model == model) & (s.parameter == pname)
            s.loc[m, "flagged"] = True
            z = float(s.loc[m, "score"].iloc[0])
            s.loc[m, "flag_reason"] = f"robust z = {z:+.1f} (> 3.5) against the lot median"
    return s


def _units_table(sessions: pd.DataFrame, lot: str, run_id: str) -> pd.DataFrame:
    rows = []
    for unit, g in sessions.groupby("unit", sort=True):
        n_ok = int((g.status == "ok").sum())
        n_w = int((g.status == "warned").sum())
        n_f = int((g.status == "failed").sum())
        rows.append(
            dict(
                lot=lot,
                unit=unit,
                state="calibrated",
                reason="",
                n_sessions=len(g),
                n_ok=n_ok,
                n_warned=n_w,
                n_failed=n_f,
                calibration_file=f"calibrations/{unit}/",
                calibrated_at=g.calibrated_at.max(),
                run_id=run_id,
                updated_at=g.calibrated_at.max(),
            )
        )
    return pd.DataFrame(rows)


def _residual_rows(rng, lot, unit, rep, bad: bool) -> list[dict]:
    rows = []
    step = 0
    # Gyro multirate: residual grows with rate for the baseline (scale nonlinearity), the
    # extended model removes most of it.
    k2 = rng.normal(0, 2e-6, 3) * (4 if bad else 1)
    for axis in range(3):
        for rate in RATES_DPS:
            for sign in (1, -1):
                w = sign * rate
                for ci, ch in enumerate(("gx", "gy", "gz")):
                    noise = rng.normal(0, 0.01)
                    base = k2[ci] * w * w * (ci == axis) + noise
                    for model, r in (("baseline", base), ("extended", noise * 1.1)):
                        rows.append(
                            dict(
                                lot=lot,
                                unit=unit,
                                rep=rep,
                                step=step,
                                test="multirate",
                                up_axis="+z",
                                rate_dps=float(w),
                                angle_deg=0.0,
                                channel=ch,
                                reference=float(w if ci == axis else 0.0),
                                residual=float(r),
                                sigma=0.01,
                                model=model,
                            )
                        )
                step += 1
    # Accel multiposition: 18 orientations (6 faces x 3 headings).
    for up in ("+x", "-x", "+y", "-y", "+z", "-z"):
        for angle in (0.0, 120.0, 240.0):
            for ci, ch in enumerate(("ax", "ay", "az")):
                ref = (1.0 if up[1] == "xyz"[ci] else 0.0) * (1 if up[0] == "+" else -1)
                noise = rng.normal(0, 1.5e-4) * (3 if bad else 1)
                for model, r in (("baseline", noise + 1e-4 * ref), ("extended", noise)):
                    rows.append(
                        dict(
                            lot=lot,
                            unit=unit,
                            rep=rep,
                            step=step,
                            test="multiposition",
                            up_axis=up,
                            rate_dps=0.0,
                            angle_deg=angle,
                            channel=ch,
                            reference=ref,
                            residual=float(r),
                            sigma=1.5e-4,
                            model=model,
                        )
                    )
            step += 1
    return rows


def _compensation_rows(rng, lot, unit, rep) -> list[dict]:
    rows = []
    # xu2016 Table 3 magnitudes (deg/s): cross-axis uncompensated errors of several deg/s.
    for ii, inp in enumerate(AXES):
        for oi, out in enumerate(AXES):
            big = 7.0 if ii != oi else 0.3
            lo = -abs(rng.normal(big, big * 0.1))
            hi = abs(rng.normal(big, big * 0.1))
            prop = abs(rng.normal(0.12, 0.02))
            for method, (a, b) in (
                ("uncompensated", (lo, hi)),
                ("proposed", (-prop, prop * 1.05)),
                ("traditional", (-prop * 1.01, prop * 1.04)),
            ):
                rows.append(
                    dict(
                        lot=lot,
                        unit=unit,
                        rep=rep,
                        input_axis=inp,
                        output_axis=out,
                        method=method,
                        err_min=float(a),
                        err_max=float(b),
                        unit_of_measure="deg/s",
                        source="verification sweep",
                    )
                )
    return rows


def _discovery_rows(rng, lot, unit, bad: bool) -> list[dict]:
    """Rows in the shape of calib_core.discovery.presentation.finding_rows."""
    before = abs(rng.normal(1.30, 0.05)) * (2.5 if bad else 1)
    rows = []
    effects = [
        (
            "gyro_scale_nonlinearity",
            "x",
            "gx",
            "q_x = 2.1 ± 0.3 deg/s per (1000 deg/s)^2; 5 others within 2 SE of 0",
            41.0,
            0.2,
        )
    ]
    if bad:
        effects.append(
            (
                "gyro_g_sensitivity",
                "z",
                "gz",
                "Gzx = 0.0040 ± 0.0006 deg/s per g; 8 others within 2 SE of 0",
                12.0,
                0.2,
            )
        )
    after = before
    for name, axes, channels, est, f_stat, frac in effects:
        new_after = after * (1 - frac)
        rows.append(
            dict(
                lot=lot,
                unit=unit,
                effect=name,
                kind="named",
                axes=axes,
                channels=channels,
                estimates=est,
                evidence=f"F = {f_stat * (1 + rng.normal(0, 0.1)):.3g} (3, 480), p = 1e-12",
                evidence_p=1e-12,
                heldout_rms_before=float(after),
                heldout_rms_after=float(new_after),
                gain=float(after / new_after),
                separated_by="",
                misfit=True,
                unexplained=bad,
                confounded_groups="",
                partial_terms="",
                negligible_terms="",
                advice="",
            )
        )
        after = new_after
    return rows


def _navigation_rows(rng, lot, unit, n: int) -> list[pd.DataFrame]:
    t = np.linspace(0, 60, n)
    parts = []
    for case, scale in (("none", 1.0), ("static", 0.08), ("static+dynamic", 0.01)):
        acc_err = scale * 9.80665 * 0.01 * (1 + rng.normal(0, 0.1))  # m/s^2
        vel = acc_err * t + np.cumsum(rng.normal(0, 2e-3 * scale, n))
        pos = np.cumsum(vel) * (t[1] - t[0])
        parts.append(
            pd.DataFrame({"lot": lot, "unit": unit, "case": case, "t": t, "vel_err": vel, "pos_err": pos})
        )
    return parts


def _write_history(root: Path, lot, units, truths, run_ids, rng, code_version) -> None:
    t_run = datetime(2026, 11, 21, 2, 0, tzinfo=UTC)
    for unit in units:
        names_g, vals_g, _, _ = truths[unit]["gyro"]
        names_a, vals_a, _, _ = truths[unit]["accel"]
        for i, rid in enumerate(run_ids):
            when = t_run - timedelta(days=len(run_ids) - 1 - i) + timedelta(minutes=units.index(unit))
            drift = len(run_ids) - 1 - i
            kg = vals_g[:9].reshape(3, 3) + rng.normal(0, 2e-5, (3, 3)) + drift * 1e-5
            w0 = vals_g[9:] + rng.normal(0, 0.004, 3) + drift * 0.01
            ka = vals_a[:9].reshape(3, 3) + rng.normal(0, 5e-5, (3, 3))
            f0 = vals_a[9:] + rng.normal(0, 2e-5, 3)
            doc = {
                "format": "mimucal-calibration",
                "format_version": "1.0",
                "kind": "turntable",
                "raw_units": {"gyro": "deg/s", "accel": "g"},
                "units": {"K_g": "deg/s per deg/s", "w0": "deg/s", "K_a": "g per g", "f0": "g"},
                "K_g": kg.tolist(),
                "w0": w0.tolist(),
                "K_a": ka.tolist(),
                "f0": f0.tolist(),
                "g_local": 9.80665,
                "terms": [],
                "metadata": {"lot": lot, "unit": unit},
                "provenance": {
                    "lot": lot,
                    "unit": unit,
                    "run_id": rid,
                    "code_version": code_version,
                    "calibrated_at": when.isoformat(),
                    "sessions": [f"lot={lot}/unit={unit}/rep={r}" for r in range(1, 6)],
                },
            }
            d = root / "calibrations" / unit
            d.mkdir(parents=True, exist_ok=True)
            (d / f"{when.strftime(TIMESTAMP_FORMAT)}.json").write_text(json.dumps(doc, indent=1))
