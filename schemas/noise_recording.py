"""Static recordings for the noise analysis (``mimucal noise``), and its output files.

A static recording is read from a contract ``samples.parquet`` (or any Parquet file with the
contract's columns and metadata) by the reader of the dataset's noise recordings
(:func:`schemas.noise_dataset.read_static_parquet`: the same checks and conversions), or
from a CSV/whitespace log through :func:`schemas.importers.read_table_recording`. Channels
come out in the noise analysis' units: gyro deg/s, accelerometer g. Raw counts
(``LSB``/``counts``) become physical with the sensor's full-scale range (``--gyro-range
250dps``, ``--accel-range 2g``; a contract file's ``gyro_range_dps``/``accel_range_g`` with
``*_full_scale_raw``), one count being range / 32768 (a signed 16-bit output) unless the
file says how many counts full scale is; the count is then the channel's output resolution.
A recording in volts, or in counts without a range, cannot give noise in engineering units:
a one-line error says so.

Outputs: the analysis JSON (:meth:`calib_core.noise.NoiseAnalysis.to_dict`) and Kalibr's
``imu.yaml`` noise figures, both written atomically.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from schemas.calibration_file import _write_text_atomic, dumps_json
from schemas.errors import SessionError
from schemas.importers import (
    ACCEL_CHANNELS,
    CHANNELS,
    FULL_SCALE_COUNTS,
    GYRO_CHANNELS,
    read_table_recording,
)
from schemas.noise_dataset import read_static_parquet

RAW_UNITS = ("LSB", "counts")


class NoiseInputError(ValueError):
    """A recording the noise analysis cannot take (one line, naming the file)."""


@dataclass(frozen=True)
class StaticRecording:
    """Channels {gx..gz: deg/s, ax..az: g} of one static recording."""

    channels: dict[str, np.ndarray]
    rate_hz: float
    source: str
    units: dict[str, str] = field(default_factory=dict)
    resolution: dict[str, float] = field(default_factory=dict)  # one count, when raw


def _physical(
    values: dict[str, np.ndarray],
    gyro_unit: str,
    accel_unit: str,
    gyro_count: float | None,
    accel_count: float | None,
    source: str,
) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Channels in deg/s and g; raw counts scaled by one count (range / counts at full scale)."""
    out, resolution = {}, {}
    for names, unit, count, kind, flag in (
        (GYRO_CHANNELS, gyro_unit, gyro_count, "gyro", "--gyro-range (e.g. 250dps)"),
        (ACCEL_CHANNELS, accel_unit, accel_count, "accelerometer", "--accel-range (e.g. 2g)"),
    ):
        if unit in RAW_UNITS:
            if count is None:
                raise NoiseInputError(
                    f"{source}: the {kind} is in raw counts: give its full-scale range {flag} "
                    "for noise in engineering units"
                )
            for ch in names:
                out[ch] = values[ch] * count
                resolution[ch] = count
        elif unit in ("deg/s", "g"):
            for ch in names:
                out[ch] = values[ch]
        else:
            raise NoiseInputError(
                f"{source}: the {kind} is in {unit!r}; the noise analysis needs deg/s, rad/s, g, "
                "m/s^2 or raw counts with a full-scale range"
            )
    return out, resolution


def read_static_recording(
    path: Path | str,
    columns: dict[str, str] | None = None,
    gyro_unit: str = "deg/s",
    accel_unit: str = "g",
    rate_hz: float | None = None,
    gyro_range_dps: float | None = None,
    accel_range_g: float | None = None,
    g_local: float = 9.80665,
    time_scale: float = 1.0,
) -> StaticRecording:
    """Read a static recording (Parquet by its suffix, else a text log); NoiseInputError or
    :class:`schemas.errors.SessionError` (one line, naming the file) on bad input."""
    path = Path(path)
    if path.suffix.lower() == ".parquet":
        return _read_parquet(path, rate_hz, gyro_range_dps, accel_range_g)
    rec = read_table_recording(path, columns, gyro_unit, accel_unit, rate_hz, g_local, time_scale)
    if not rec.rate_hz or not np.isfinite(rec.rate_hz) or rec.rate_hz <= 0:
        raise NoiseInputError(f"{path.name}: no sample rate: give --rate")
    values = {ch: rec.samples[ch].to_numpy(float) for ch in CHANNELS}
    gcount = None if gyro_range_dps is None else gyro_range_dps / FULL_SCALE_COUNTS
    acount = None if accel_range_g is None else accel_range_g / FULL_SCALE_COUNTS
    channels, resolution = _physical(values, rec.gyro_unit, rec.accel_unit, gcount, acount, path.name)
    units = {ch: ("deg/s" if ch in GYRO_CHANNELS else "g") for ch in CHANNELS}
    return StaticRecording(channels, float(rec.rate_hz), path.name, units, resolution)


def _read_parquet(
    path: Path, rate_hz: float | None, gyro_range_dps: float | None, accel_range_g: float | None
) -> StaticRecording:
    """The fleet's reader of static Parquet recordings
    (:func:`schemas.noise_dataset.read_static_parquet`: its checks and unit conversions),
    then raw counts made physical with the ranges given or the file's."""
    rec = read_static_parquet(path, path.name)
    md = rec.meta
    values = {ch: v for ch, v in zip(CHANNELS, np.hstack([rec.gyro, rec.accel]).T)}
    rate = rate_hz or rec.rate_hz

    def count(range_arg, range_md, full_md):
        if range_arg is not None:
            return range_arg / FULL_SCALE_COUNTS
        full = np.asarray(full_md if full_md is not None else (FULL_SCALE_COUNTS,) * 3, float)
        return float(np.mean(np.asarray(range_md, float) / full))

    gcount = count(gyro_range_dps, md.gyro_range_dps, md.gyro_full_scale_raw)
    acount = count(accel_range_g, md.accel_range_g, md.accel_full_scale_raw)
    channels, resolution = _physical(values, md.gyro_unit, md.accel_unit, gcount, acount, path.name)
    units = {ch: ("deg/s" if ch in GYRO_CHANNELS else "g") for ch in CHANNELS}
    return StaticRecording(channels, float(rate), path.name, units, resolution)


def write_noise_json(path: Path | str, doc: dict) -> None:
    """The analysis document (NaN/inf as null), atomically."""
    _write_text_atomic(Path(path), dumps_json(doc, nonfinite="null"))


KALIBR_KEYS = (
    "accelerometer_noise_density",
    "accelerometer_random_walk",
    "gyroscope_noise_density",
    "gyroscope_random_walk",
)


def kalibr_yaml(figures: dict, source: str) -> str:
    """Kalibr's imu.yaml noise block from :meth:`NoiseAnalysis.kalibr` figures."""
    lines = [
        f"# IMU noise of {source}, measured by mimucal noise",
        "# Continuous-time noise densities in SI, as Kalibr's imu.yaml wants them; the",
        "# discrete-time standard deviation of one sample is density * sqrt(update_rate).",
        "# Each figure is the largest of the sensor's three axes.",
        "rostopic: /imu0  # set to your IMU topic",
        f"update_rate: {figures['update_rate']:.6g}  # Hz",
    ]
    for key in KALIBR_KEYS:
        if key not in figures:
            continue
        note = figures.get(key + "_note")
        unit = figures[key + "_unit"]
        lines.append(f"{key}: {figures[key]:.6e}  # {unit}, continuous-time" + (f"; {note}" if note else ""))
    return "\n".join(lines) + "\n"


def write_kalibr_yaml(path: Path | str, figures: dict, source: str) -> None:
    _write_text_atomic(Path(path), kalibr_yaml(figures, source))


__all__ = [
    "NoiseInputError",
    "SessionError",
    "StaticRecording",
    "kalibr_yaml",
    "read_static_recording",
    "write_kalibr_yaml",
    "write_noise_json",
]
