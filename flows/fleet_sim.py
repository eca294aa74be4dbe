"""Simulate a fleet of units on the turntable and write it as a dataset in the contract,
with a manifest (``fleet.json``) of the truth, the injected outliers and the sessions made bad.

Population model (deterministic for a seed; every unit has its own child seed, so a unit's
data do not depend on how many units were simulated before it):

- each lot has a lot-mean unit drawn by :func:`calib_core.sim.simulator.typical_truth` (K near
  identity, 1 % scale and cross-axis terms, 0.5 deg/s and 5 mg biases);
- each unit scatters around its lot mean: K_g and K_a diagonal sd ``UNIT_SPREAD['k_diag']``
  (0.003), off-diagonal sd 0.002, w0 sd 0.05 deg/s, f0 sd 1 mg;
- each repetition moves the biases by the turn-on repeatability (0.01 deg/s, 0.1 mg).

Outliers (``outliers=K``): K distinct units get one parameter shifted far beyond the lot
spread, cycling through ``OUTLIER_KINDS`` (k_g11 +0.04 = 13 sd; w0_z +0.8 deg/s = 16 sd;
k_a22 +0.04). Bad sessions (``bad_sessions=K``): K distinct sessions are damaged after
writing, cycling through ``BAD_KINDS``, each with the error code the reader must give.

The truth in the manifest is in mimucal's inside units (w = K_g G + w0 in deg/s, f = K_a A +
f0 in g) whatever units the files are written in: the reader converts rad/s and m/s^2 back.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from dataclasses import replace
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from calib_core.sim import protocols
from calib_core.sim.simulator import (
    MimuTruth,
    draw_repetition_truth,
    session_metadata,
    simulate_session,
    typical_truth,
)
from calib_core.steps import SessionKey
from schemas.contract import SAMPLES_FILE, STEPS_FILE
from schemas.errors import (
    E_MISSING_FILE,
    E_NONFINITE_VALUE,
    E_NONINCREASING_TIME,
    E_UNKNOWN_UNIT,
    E_UNREADABLE_FILE,
)
from schemas.writer import write_session

MANIFEST = "fleet.json"
MANIFEST_FORMAT = "mimucal-fleet"
MANIFEST_VERSION = "1.0"

UNIT_SPREAD = {"k_diag": 0.003, "k_offdiag": 0.002, "w0_dps": 0.05, "f0_g": 1e-3}
REPEATABILITY = {"gyro_bias_repeatability_dps": 0.01, "accel_bias_repeatability_g": 1e-4}

# (name, matrix/vector attribute, index, shift)
OUTLIER_KINDS = (
    # >= 10 lot standard deviations: the lot flags hold a ~1 % family-wise false-alarm rate,
    # so smaller shifts are found only part of the time (docs/flows.md)
    ("k_g11", "K_g", (0, 0), 0.04),
    ("w0_z", "w0", (2,), 0.8),
    ("k_a22", "K_a", (1, 1), 0.04),
)
BAD_KINDS = {
    "nan_burst": (E_NONFINITE_VALUE, "20 NaN samples in gx inside a multirate step"),
    "truncated_samples": (E_UNREADABLE_FILE, "samples.parquet cut to half its size"),
    "missing_steps": (E_MISSING_FILE, "steps.parquet deleted"),
    "nonincreasing_time": (E_NONINCREASING_TIME, "two consecutive t values swapped"),
    "unknown_unit": (E_UNKNOWN_UNIT, "gyro_unit metadata set to 'dps'"),
}

TruthFactory = Callable[[np.random.Generator, str, str], MimuTruth]


def _spread(M: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    noise = rng.normal(0.0, UNIT_SPREAD["k_offdiag"], (3, 3))
    noise[np.diag_indices(3)] = rng.normal(0.0, UNIT_SPREAD["k_diag"], 3)
    return M + noise


def unit_truth(lot_truth: MimuTruth, rng: np.random.Generator) -> MimuTruth:
    """One unit scattered around its lot mean (see module docstring)."""
    return replace(
        lot_truth,
        K_g=_spread(lot_truth.K_g, rng),
        K_a=_spread(lot_truth.K_a, rng),
        w0=lot_truth.w0 + rng.normal(0.0, UNIT_SPREAD["w0_dps"], 3),
        f0=lot_truth.f0 + rng.normal(0.0, UNIT_SPREAD["f0_g"], 3),
        **REPEATABILITY,
    )


def _inject_outlier(truth: MimuTruth, kind: tuple) -> MimuTruth:
    name, attr, index, shift = kind
    value = np.array(getattr(truth, attr), dtype=float, copy=True)
    value[index] += shift
    return replace(truth, **{attr: value})


def _truth_doc(truth: MimuTruth) -> dict:
    return {
        "K_g": np.asarray(truth.K_g).tolist(),
        "w0": np.asarray(truth.w0).tolist(),
        "K_a": np.asarray(truth.K_a).tolist(),
        "f0": np.asarray(truth.f0).tolist(),
    }


def _write_json_atomic(path: Path, doc: dict) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as fh:
            json.dump(doc, fh, indent=2, allow_nan=False)
            fh.write("\n")
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def damage_session(path: Path, kind: str, steps: pd.DataFrame, rng: np.random.Generator) -> str:
    """Make one written session invalid in the named way; returns a short description."""
    samples = path / SAMPLES_FILE
    if kind == "truncated_samples":
        data = samples.read_bytes()
        samples.write_bytes(data[: len(data) // 2])
    elif kind == "missing_steps":
        (path / STEPS_FILE).unlink()
    elif kind in ("nan_burst", "nonincreasing_time", "unknown_unit"):
        table = pq.read_table(samples)
        md = dict(table.schema.metadata or {})
        df = table.to_pandas()
        if kind == "nan_burst":
            multirate = steps.loc[steps["test"] == "multirate", "step"].to_numpy()
            target = int(rng.choice(multirate))
            rows = np.flatnonzero(df["step"].to_numpy() == target)
            start = rows[len(rows) // 2]
            df.loc[start : start + 19, "gx"] = np.nan
        elif kind == "nonincreasing_time":
            i = int(rng.integers(1, len(df) - 1))
            t = df["t"].to_numpy(copy=True)
            t[i], t[i + 1] = t[i + 1], t[i]
            df["t"] = t
        else:
            md[b"gyro_unit"] = b"dps"
        # numpy arrays, not from_pandas: a NaN must stay a NaN in the file, not become null
        out = pa.Table.from_arrays(
            [pa.array(df[f.name].to_numpy(), type=f.type) for f in table.schema],
            schema=table.schema.with_metadata(md),
        )
        pq.write_table(out, samples, compression="zstd", use_dictionary=False)
    else:
        raise ValueError(f"unknown bad-session kind {kind!r} (known: {', '.join(BAD_KINDS)})")
    return BAD_KINDS[kind][1]


SIM_FIRST_SESSION = datetime(2026, 11, 20, 2, 0, tzinfo=UTC)


def simulate_fleet(
    out: Path | str,
    lots: int,
    units: int,
    reps: int,
    seed: int,
    sample_rate_hz: float = 100.0,
    outliers: int = 0,
    bad_sessions: int = 0,
    verification: bool = False,
    gyro_unit: str | None = None,
    accel_unit: str | None = None,
    protocol: pd.DataFrame | None = None,
    truth_factory: TruthFactory | None = None,
    noise_recording_s: float = 0.0,
    noisy_units: int = 0,
    noise_factor: float = 3.0,
    noise_from: dict | None = None,
) -> dict:
    """Write ``lots`` lots x ``units`` units per lot x ``reps`` repetitions under ``out`` and
    the manifest ``out/fleet.json``; return the manifest.

    Noise (docs/noise.md): ``noise_recording_s`` > 0 writes a static recording of that length
    per unit (``lot=L/unit=U/noise/static.parquet``, :func:`_noise_recordings`);
    ``noisy_units`` distinct units get ``noise_factor`` times the lot's gyro white noise
    (angle random walk) in their sessions and recordings; ``noise_from`` (a ``mimucal noise
    --json`` document) makes the recordings' noise the measured model's (periodic lines and
    quantization included) and the sessions' white noise its white coefficients.

    ``protocol``: a step table (default :func:`calib_core.sim.protocols.default_session`, with the
    verification sweep when ``verification``). ``truth_factory(rng, lot, unit)`` replaces the
    population model (outliers are still injected on top). Unit ids ``U0001..`` are numbered
    across the fleet (a unit belongs to one lot), lots ``L01..``.
    """
    if lots < 1 or units < 1 or reps < 1:
        raise ValueError("lots, units and reps must be >= 1")
    n_units = lots * units
    if not 0 <= outliers <= n_units:
        raise ValueError(f"outliers={outliers} must be between 0 and the {n_units} units")
    if not 0 <= bad_sessions <= n_units * reps:
        raise ValueError(f"bad_sessions={bad_sessions} must be between 0 and the {n_units * reps} sessions")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    steps = protocol if protocol is not None else protocols.default_session(verification=verification)
    root_seq = np.random.SeedSequence(seed)
    lot_seqs = root_seq.spawn(lots)
    pick_rng = np.random.default_rng(root_seq.spawn(1)[0])  # which units/sessions are special
    outlier_units = set(pick_rng.choice(n_units, size=outliers, replace=False).tolist())
    outlier_order = sorted(outlier_units)
    bad_flat = pick_rng.choice(n_units * reps, size=bad_sessions, replace=False).tolist()
    bad_kinds = list(BAD_KINDS)
    bad_of = {int(s): bad_kinds[i % len(bad_kinds)] for i, s in enumerate(sorted(bad_flat))}
    if not 0 <= noisy_units <= n_units:
        raise ValueError(f"noisy_units={noisy_units} must be between 0 and the {n_units} units")
    if noisy_units and not noise_factor > 0:
        raise ValueError(f"noise_factor={noise_factor} must be > 0")
    noisy = set(pick_rng.choice(n_units, size=noisy_units, replace=False).tolist()) if noisy_units else set()
    noise_model = _measured_noise(noise_from, sample_rate_hz) if noise_from is not None else None

    manifest: dict = {
        "format": MANIFEST_FORMAT,
        "format_version": MANIFEST_VERSION,
        "seed": seed,
        "lots": lots,
        "units_per_lot": units,
        "reps": reps,
        "sample_rate_hz": sample_rate_hz,
        "n_steps": int(len(steps)),
        "verification": bool(verification),
        "file_units": {"gyro": gyro_unit or "deg/s", "accel": accel_unit or "g"},
        "truth_units": {"K_g": "deg/s per deg/s", "w0": "deg/s", "K_a": "g per g", "f0": "g"},
        "unit_spread": UNIT_SPREAD,
        "repeatability": REPEATABILITY,
        "lot_truth": {},
        "units": [],
        "outliers": [],
        "bad_sessions": [],
        "noise": {
            "recording_s": noise_recording_s,
            "noisy_units": [],
            "noise_factor": noise_factor if noisy_units else None,
            "noise_from": None if noise_model is None else noise_model.source,
        },
    }
    for li, lot_seq in enumerate(lot_seqs):
        lot = f"L{li + 1:02d}"
        lot_rng, *unit_seqs = [np.random.default_rng(s) for s in lot_seq.spawn(units + 1)]
        lot_truth = typical_truth(lot_rng)
        manifest["lot_truth"][lot] = _truth_doc(lot_truth)
        for ui, unit_rng in enumerate(unit_seqs):
            flat_unit = li * units + ui
            unit = f"U{flat_unit + 1:04d}"
            truth = truth_factory(unit_rng, lot, unit) if truth_factory else unit_truth(lot_truth, unit_rng)
            outlier = None
            if flat_unit in outlier_units:
                kind = OUTLIER_KINDS[outlier_order.index(flat_unit) % len(OUTLIER_KINDS)]
                truth = _inject_outlier(truth, kind)
                outlier = {"param": kind[0], "shift": kind[3]}
                manifest["outliers"].append({"lot": lot, "unit": unit, **outlier})
            if noise_model is not None:
                truth = replace(truth, gyro_noise_dps=noise_model.gyro_sd, accel_noise_g=noise_model.accel_sd)
            factor = noise_factor if flat_unit in noisy else 1.0
            if flat_unit in noisy:  # N times the lot's angle random walk
                truth = replace(truth, gyro_noise_dps=np.asarray(truth.gyro_noise_dps, float) * factor)
                manifest["noise"]["noisy_units"].append({"lot": lot, "unit": unit, "factor": factor})
            unit_doc = {"lot": lot, "unit": unit, "truth": _truth_doc(truth), "outlier": outlier, "reps": []}
            for rep in range(1, reps + 1):
                key = SessionKey(lot, unit, rep)
                rep_truth = draw_repetition_truth(truth, unit_rng)
                samples = simulate_session(rep_truth, steps, unit_rng, sample_rate_hz)
                # lot k is acquired on day k from 2026-11-20 02:00 UTC, its units one after
                # the other, a minute per repetition (acquisition order: trends, history)
                start = SIM_FIRST_SESSION + timedelta(days=li, minutes=ui * reps + rep - 1)
                md = session_metadata(
                    rep_truth,
                    sample_rate_hz,
                    session_start=start.strftime("%Y-%m-%dT%H:%M:%SZ"),
                    lot=lot,
                    unit=unit,
                    rep=str(rep),
                    seed=str(seed),
                )
                path = write_session(out, key, steps, samples, md, gyro_unit, accel_unit)
                rep_doc = {
                    "rep": rep,
                    "path": str(path.relative_to(out)),
                    "w0": np.asarray(rep_truth.w0).tolist(),
                    "f0": np.asarray(rep_truth.f0).tolist(),
                    "bad": None,
                }
                flat_session = flat_unit * reps + (rep - 1)
                if flat_session in bad_of:
                    kind = bad_of[flat_session]
                    # its own generator: damaging a session does not change the next ones
                    detail = damage_session(path, kind, steps, np.random.default_rng([seed, flat_session]))
                    bad = {"kind": kind, "expected_code": BAD_KINDS[kind][0], "detail": detail}
                    rep_doc["bad"] = bad
                    manifest["bad_sessions"].append(
                        {"session": str(key), "lot": lot, "unit": unit, "rep": rep, **bad}
                    )
                unit_doc["reps"].append(rep_doc)
            if noise_recording_s > 0:
                unit_doc["noise_recording"] = _noise_recordings(
                    out,
                    lot,
                    unit,
                    truth,
                    noise_recording_s,
                    sample_rate_hz,
                    unit_rng,
                    noise_model,
                    factor,
                    seed,
                )
            manifest["units"].append(unit_doc)
    _write_json_atomic(out / MANIFEST, manifest)
    return manifest


class _MeasuredNoise:
    """A ``mimucal noise --json`` document as the simulator uses it: the model
    (:class:`calib_core.noise.NoiseModel`) and the per-sample white sd of each channel at
    the fleet's sample rate (deg/s, g) for the sessions."""

    def __init__(self, doc: dict, rate_hz: float) -> None:
        from calib_core.noise import NoiseModel

        self.model = NoiseModel.from_dict(doc)
        self.source = str(doc.get("source") or doc.get("recording") or "a measured noise model")
        default = MimuTruth()
        sd = []
        for i, ch in enumerate(("gx", "gy", "gz", "ax", "ay", "az")):
            ch_doc = (doc.get("channels") or {}).get(ch)
            if ch_doc is None:  # a channel the model lacks: the simulator's own white noise
                sd.append(default.gyro_noise_dps if i < 3 else default.accel_noise_g)
                continue
            white = (ch_doc.get("coefficients") or {}).get("white") or {}
            sd.append(_white_sd_per_sample(white, ch, rate_hz))
        self.gyro_sd, self.accel_sd = np.array(sd[:3]), np.array(sd[3:])

    def record(self, n: int, rate_hz: float, rng: np.random.Generator, fallback_sd: np.ndarray) -> np.ndarray:
        """(n, 6) noise in deg/s and g; a channel the model lacks gets white noise of
        ``fallback_sd``."""
        from calib_core.noise import synthesize

        chans = synthesize(self.model, n, rate_hz, rng)
        out = np.empty((n, 6))
        for i, c in enumerate(("gx", "gy", "gz", "ax", "ay", "az")):
            if c not in chans:
                out[:, i] = rng.normal(0.0, fallback_sd[i], n)
                continue
            unit = self.model.channels[c].unit
            scale = {"rad/s": 180.0 / np.pi, "m/s^2": 1.0 / 9.80665, "m/s2": 1.0 / 9.80665}.get(unit, 1.0)
            out[:, i] = np.asarray(chans[c], float) * scale
        return out


def _white_sd_per_sample(white: dict, channel: str, rate_hz: float) -> float:
    """The per-sample sd (deg/s or g) of a white coefficient (deg/sqrt(h) or m/s/sqrt(h)) at
    ``rate_hz``: density = coefficient / 60 per sqrt(Hz), sd = density sqrt(rate)."""
    value = white.get("value")
    if value is None:
        return 0.0
    density = float(value) / 60.0
    if channel.startswith("a"):
        density /= 9.80665  # m/s^2/sqrt(Hz) -> g/sqrt(Hz)
    return density * np.sqrt(rate_hz)


def _measured_noise(doc: dict, rate_hz: float) -> _MeasuredNoise:
    return _MeasuredNoise(doc, rate_hz)


def _noise_recordings(
    out: Path,
    lot: str,
    unit: str,
    truth: MimuTruth,
    duration_s: float,
    rate_hz: float,
    rng: np.random.Generator,
    measured: _MeasuredNoise | None,
    factor: float,
    seed: int,
) -> dict:
    """Write the unit's static recording ``noise/static.parquet``; its manifest entry."""
    from calib_core.sim.noise_recording import static_noise_recording
    from schemas.writer import write_noise_recording

    n = int(round(duration_s * rate_hz))
    noise = None
    if measured is not None:
        fallback = np.concatenate(
            [np.broadcast_to(truth.gyro_noise_dps, 3), np.broadcast_to(truth.accel_noise_g, 3)]
        )
        noise = measured.record(n, rate_hz, rng, fallback)
        if factor != 1.0:  # more white noise on the gyros: N^2 - 1 times its variance, added
            extra = np.sqrt(max(factor**2 - 1.0, 0.0)) * np.asarray(measured.gyro_sd)
            noise[:, :3] += rng.normal(0.0, 1.0, (n, 3)) * extra
    samples = static_noise_recording(truth, duration_s, rate_hz, rng, noise=noise)
    md = session_metadata(
        truth,
        rate_hz,
        session_start=SIM_FIRST_SESSION.strftime("%Y-%m-%dT%H:%M:%SZ"),
        lot=lot,
        unit=unit,
        seed=str(seed),
        recording="static, unit at rest, z up",
    )
    path = write_noise_recording(out, lot, unit, "static", samples, md)
    return {
        "path": str(path.relative_to(out)),
        "duration_s": duration_s,
        "rate_hz": rate_hz,
        "gyro_white_sd_dps": np.asarray(truth.gyro_noise_dps, float).tolist(),
        "accel_white_sd_g": np.asarray(truth.accel_noise_g, float).tolist(),
        "arw_factor": factor,
    }


def simulate_physics_fleet(
    out: Path | str,
    lots: int,
    units: int,
    reps: int,
    seed: int,
    sample_rate_hz: float = 50.0,
    hide: tuple[tuple[str, float], ...] = (),
    tilted: bool = True,
    latitude_deg: float | None = None,
    declare_location: bool = False,
    back_to_back: bool = False,
) -> dict:
    """A fleet of :mod:`calib_core.sim.physics` units (each sensor its own misaligned axis,
    noise processes, warm-up ramp) with the catalogue effects ``hide`` = ((name, scale), ...)
    hidden in every unit at ``scale`` times a realistic size, written in the contract with
    the manifest ``out/fleet.json`` (the hidden parameters per unit). ``tilted=False`` leaves
    out zhang2017's dynamic steps on the 45-degree diagonals; ``latitude_deg`` adds the Earth
    rate (and writes the location into the metadata with ``declare_location``);
    ``back_to_back`` runs a unit's repetitions one after the other on one warm-up (each at
    its own temperature) instead of a cold start a day."""
    from calib_core.effects import get_effect
    from calib_core.sim.physics import Turntable, typical_physics_unit
    from schemas.physics_sessions import write_physics_unit

    if lots < 1 or units < 1 or reps < 1:
        raise ValueError("lots, units and reps must be >= 1")
    terms = [(get_effect(name), float(scale)) for name, scale in hide]  # KeyError: unknown
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows = protocols.xu2016_multirate() + protocols.xu2016_multiposition()
    rows += protocols.dynamic_steps(tilted=tilted)
    steps = protocols.to_frame(rows)
    table = Turntable(latitude_deg=latitude_deg, declare_location=declare_location)
    manifest: dict = {
        "format": MANIFEST_FORMAT,
        "format_version": MANIFEST_VERSION,
        "seed": seed,
        "simulator": "physics",
        "lots": lots,
        "units_per_lot": units,
        "reps": reps,
        "sample_rate_hz": sample_rate_hz,
        "n_steps": int(len(steps)),
        "tilted_steps": tilted,
        "latitude_deg": latitude_deg,
        "declare_location": declare_location,
        "repetitions": "back to back on one warm-up" if back_to_back else "a cold start each",
        "file_units": {"gyro": "deg/s", "accel": "g"},
        "hidden": [{"effect": t.name, "scale": s} for t, s in terms],
        "units": [],
        "outliers": [],
        "bad_sessions": [],
    }
    seqs = np.random.SeedSequence(seed).spawn(lots * units)
    for flat, seq in enumerate(seqs):
        rng = np.random.default_rng(seq)
        lot, unit_id = f"L{flat // units + 1:02d}", f"U{flat + 1:04d}"
        unit = typical_physics_unit(rng)
        effects = []
        for term, scale in terms:
            unit, theta, what = term.hide(unit, rng, scale)
            effects.append(
                {
                    "effect": term.name,
                    "scale": scale,
                    "where": what,
                    "params": dict(zip(term.param_names, np.asarray(theta).tolist())),
                    "units": dict(zip(term.param_names, term.param_units)),
                }
            )
        write_physics_unit(
            out,
            unit,
            steps,
            rng,
            n_reps=reps,
            rate_hz=sample_rate_hz,
            table=table,
            lot=lot,
            unit_id=unit_id,
            back_to_back=back_to_back,
        )
        manifest["units"].append({"lot": lot, "unit": unit_id, "hidden": effects})
    _write_json_atomic(out / MANIFEST, manifest)
    return manifest
