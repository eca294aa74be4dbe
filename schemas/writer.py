"""Write one session in the contract: ``steps.parquet`` and ``samples.parquet``.

Samples are written without dictionary encoding (it bloats random floats by 6-47 %) and with
zstd; the key-value metadata goes into the Parquet schema metadata of samples.parquet.
Optional unit conversion on write (deg/s -> rad/s, g -> m/s^2 with ``g_local``) produces the
same data as an acquisition system that records SI units. Each file is written to a temp
file in the session directory and renamed into place (``os.replace``), so a reader never sees
a half-written file.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from calib_core.steps import SessionKey
from schemas.contract import (
    ACCEL_COLUMNS,
    ACCEL_UNITS,
    G_LOCAL_DEFAULT,
    GYRO_COLUMNS,
    GYRO_UNITS,
    RAD_TO_DEG,
    SAMPLES_FILE,
    SAMPLES_OPTIONAL,
    SAMPLES_SCHEMA,
    STEPS_FILE,
    STEPS_OPTIONAL,
    STEPS_SCHEMA,
)
from schemas.dataset import session_dir
from schemas.hive import NOISE_DIR, id_problem
from schemas.noise_dataset import NOISE_SUFFIX


def _atomic_write(table: pa.Table, path: Path, **kwargs) -> None:
    """Parquet with a CRC32 per data page (verified by the reader): bytes damaged after the
    file was written are found even where they still decode."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        pq.write_table(table, tmp, write_page_checksum=True, **kwargs)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def steps_table(steps_df: pd.DataFrame) -> pa.Table:
    """The contract's steps table (+ the optional columns the frame has)."""
    fields = list(STEPS_SCHEMA)
    fields += [pa.field(c, t) for c, t in STEPS_OPTIONAL.items() if c in steps_df.columns]
    schema = pa.schema(fields)
    arrays = []
    for f in schema:
        col = steps_df[f.name]
        if pa.types.is_string(f.type):
            arrays.append(pa.array(col.astype(str).tolist(), type=f.type))
        else:
            arrays.append(pa.array(col.to_numpy(dtype=f.type.to_pandas_dtype()), type=f.type))
    return pa.Table.from_arrays(arrays, schema=schema)


def samples_table(
    samples_df: pd.DataFrame, metadata: Mapping[str, str], gyro_scale: float = 1.0, accel_scale: float = 1.0
) -> pa.Table:
    """Samples in the contract; sensor columns keep their float32/float64 dtype; the values
    are multiplied by ``gyro_scale`` / ``accel_scale`` (unit conversion on write)."""
    arrays, fields = [], []
    for f in SAMPLES_SCHEMA:
        values = samples_df[f.name].to_numpy()
        if f.name in GYRO_COLUMNS + ACCEL_COLUMNS:
            dtype = values.dtype if values.dtype in (np.float32, np.float64) else np.float32
            scale = gyro_scale if f.name in GYRO_COLUMNS else accel_scale
            values = (
                (values.astype(np.float64) * scale).astype(dtype)
                if scale != 1.0
                else values.astype(dtype, copy=False)
            )
            f = pa.field(f.name, pa.from_numpy_dtype(dtype))
        else:
            values = values.astype(f.type.to_pandas_dtype(), copy=False)
        arrays.append(pa.array(values, type=f.type))
        fields.append(f)
    if "temp_c" in samples_df.columns:
        fields.append(pa.field("temp_c", SAMPLES_OPTIONAL["temp_c"]))
        arrays.append(pa.array(samples_df["temp_c"].to_numpy(np.float32)))
    schema = pa.schema(fields, metadata={str(k): str(v) for k, v in metadata.items()})
    return pa.Table.from_arrays(arrays, schema=schema)


def write_session(
    root: Path | str,
    key: SessionKey,
    steps_df: pd.DataFrame,
    samples_df: pd.DataFrame,
    metadata: Mapping[str, str],
    gyro_unit: str | None = None,
    accel_unit: str | None = None,
) -> Path:
    """Write ``<root>/lot=/unit=/rep=/{steps,samples}.parquet`` and return the directory.

    ``metadata`` describes ``samples_df`` as given (its ``gyro_unit``/``accel_unit``).
    ``gyro_unit="rad/s"`` converts deg/s samples to rad/s, ``accel_unit="m/s^2"`` converts g to
    m/s^2 with the metadata's ``g_local``; the metadata is updated to match. Converting from a
    raw unit (LSB, V) is refused: there is no known factor.
    """
    md = {str(k): str(v) for k, v in metadata.items()}
    gyro_scale = accel_scale = 1.0
    if gyro_unit is not None and gyro_unit != md.get("gyro_unit"):
        if gyro_unit not in GYRO_UNITS:
            raise ValueError(f"gyro_unit {gyro_unit!r} is not one of {', '.join(GYRO_UNITS)}")
        if (md.get("gyro_unit"), gyro_unit) == ("deg/s", "rad/s"):
            gyro_scale = 1.0 / RAD_TO_DEG
        elif (md.get("gyro_unit"), gyro_unit) == ("rad/s", "deg/s"):
            gyro_scale = RAD_TO_DEG
        else:
            raise ValueError(f"cannot convert gyro samples from {md.get('gyro_unit')!r} to {gyro_unit!r}")
        md["gyro_unit"] = gyro_unit
    if accel_unit is not None and accel_unit != md.get("accel_unit"):
        if accel_unit not in ACCEL_UNITS:
            raise ValueError(f"accel_unit {accel_unit!r} is not one of {', '.join(ACCEL_UNITS)}")
        g_local = float(md.get("g_local", G_LOCAL_DEFAULT))
        if (md.get("accel_unit"), accel_unit) == ("g", "m/s^2"):
            accel_scale = g_local
        elif (md.get("accel_unit"), accel_unit) == ("m/s^2", "g"):
            accel_scale = 1.0 / g_local
        else:
            raise ValueError(f"cannot convert accel samples from {md.get('accel_unit')!r} to {accel_unit!r}")
        md["accel_unit"] = accel_unit
    out = session_dir(root, key)
    out.mkdir(parents=True, exist_ok=True)
    _atomic_write(steps_table(steps_df), out / STEPS_FILE, compression="zstd")
    _atomic_write(
        samples_table(samples_df, md, gyro_scale, accel_scale),
        out / SAMPLES_FILE,
        compression="zstd",
        use_dictionary=False,
    )
    return out


def write_noise_recording(
    root: Path | str, lot: str, unit: str, name: str, samples: pd.DataFrame, metadata: dict[str, str]
) -> Path:
    """Write ``<root>/lot=<lot>/unit=<unit>/noise/<name>.parquet`` (atomically) from raw
    samples (``t``, ``gx..az``; ``step`` written as -1 when absent) with the key-value
    ``metadata`` of samples.parquet. Returns the file."""
    for field_name, value in (("lot", lot), ("unit", unit), ("recording", name)):
        why = id_problem(value, field_name)
        if why:
            raise ValueError(why)
    df = samples if "step" in samples.columns else samples.assign(step=np.int32(-1))
    out = Path(root) / f"lot={lot}" / f"unit={unit}" / NOISE_DIR
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{name}{NOISE_SUFFIX}"
    _atomic_write(samples_table(df, metadata), path, compression="zstd", use_dictionary=False)
    return path
