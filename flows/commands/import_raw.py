"""`mimucal import-raw FILE --columns gx=...,... --gyro-unit U --accel-unit U --out OUT`:
read a CSV/whitespace export of any IMU into mimucal's layout for recordings without
turntable references (t, gx..gz, ax..az; units converted at the boundary), detect the static
poses and optionally write their means (the input of model discovery on real data)."""

from __future__ import annotations

import json
from fractions import Fraction
from pathlib import Path

from flows.cli import CliError

GYRO_UNIT_CHOICES = ("deg/s", "rad/s", "LSB", "counts", "V")
ACCEL_UNIT_CHOICES = ("g", "mg", "m/s^2", "LSB", "counts", "V")


def number(text: str) -> float:
    """A float or a fraction such as ``1/6258``."""
    try:
        return float(Fraction(text.strip())) if "/" in text else float(text)
    except (ValueError, ZeroDivisionError) as exc:
        raise CliError(f"not a number: {text!r}") from exc


def add_table_options(p, default_columns: str | None = None) -> None:
    p.add_argument(
        "--columns",
        default=default_columns,
        metavar="MAP",
        help="column mapping CHANNEL=SOURCE for gx,gy,gz,ax,ay,az (and optional t), "
        "e.g. gx=gyr_x,gy=gyr_y,gz=gyr_z,ax=acc_x,ay=acc_y,az=acc_z; for a "
        "header-less whitespace file SOURCE is the 0-based column position; "
        "optional when the header names the channels ax,ay,az,gx,gy,gz"
        + (f" (default {default_columns})" if default_columns else ""),
    )
    p.add_argument(
        "--rate",
        type=float,
        default=None,
        metavar="HZ",
        help="sample rate (when no time column t is mapped and the file's preamble has no Fs line)",
    )
    p.add_argument(
        "--time-scale",
        type=float,
        default=1.0,
        metavar="F",
        help="multiply the time column by F to get seconds (default 1)",
    )


def read_table_args(args, path: Path, default_gyro: str, default_accel: str, g_local: float):
    """The table named on the command line; without --columns the header must name the
    channels (ax,ay,az,gx,gy,gz)."""
    from schemas.errors import SessionError
    from schemas.importers import parse_column_mapping, read_table_recording

    try:
        mapping = parse_column_mapping(args.columns) if args.columns else None
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    if args.rate is not None and args.rate <= 0:
        raise CliError("--rate must be > 0")
    try:
        return read_table_recording(
            path,
            mapping,
            args.gyro_unit or default_gyro,
            args.accel_unit or default_accel,
            rate_hz=args.rate,
            g_local=g_local,
            time_scale=args.time_scale,
        )
    except SessionError as exc:
        raise CliError(str(exc)) from exc


def register(sub) -> None:
    p = sub.add_parser(
        "import-raw",
        help="import a CSV/whitespace IMU export (no turntable references)",
        description="Read FILE with a column mapping into mimucal's reference-free layout "
        "(t [s], gx gy gz [deg/s or raw], ax ay az [g or raw]) and write it to OUT "
        "(.csv or .parquet) with a sidecar OUT.json of units; optionally detect "
        "the static poses and write their means to --poses.",
    )
    p.add_argument("file", type=Path, metavar="FILE")
    add_table_options(p)
    p.add_argument("--gyro-unit", choices=GYRO_UNIT_CHOICES, required=True)
    p.add_argument("--accel-unit", choices=ACCEL_UNIT_CHOICES, required=True)
    p.add_argument(
        "--g-local",
        type=float,
        default=9.80665,
        metavar="M_S2",
        help="local gravity used to convert m/s^2 to g (default 9.80665)",
    )
    p.add_argument("--out", type=Path, default=None, help="write the imported samples here")
    p.add_argument(
        "--poses", type=Path, default=None, metavar="CSV", help="write the detected static poses' means here"
    )
    p.add_argument(
        "--init-static",
        type=float,
        default=None,
        metavar="S",
        help="the recording starts with S seconds at rest: noise floor from it "
        "(default: 5%% quantile of the windowed variance)",
    )
    p.add_argument(
        "--multiplier", type=float, default=6.0, help="threshold = multiplier x noise floor (default 6)"
    )
    p.add_argument("--window", type=int, default=101, metavar="N", help="variance window, samples")
    p.set_defaults(func=run)


def run(args) -> int:
    import numpy as np

    from calib_core.models.field.static_detection import detect_static, static_pose_means

    rec = read_table_args(args, args.file, args.gyro_unit, args.accel_unit, args.g_local)
    print(
        f"{rec.source}: {len(rec)} samples, {rec.rate_hz:.4g} Hz, gyro {rec.gyro_unit}, "
        f"accel {rec.accel_unit}"
    )
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        if args.out.suffix == ".parquet":
            # page checksums, verified when the file is read (schemas.reader)
            rec.samples.to_parquet(args.out, index=False, write_page_checksum=True)
        else:
            rec.samples.to_csv(args.out, index=False)
        args.out.with_suffix(args.out.suffix + ".json").write_text(
            json.dumps(
                {
                    "layout": "mimucal-raw-recording",
                    "gyro_unit": rec.gyro_unit,
                    "accel_unit": rec.accel_unit,
                    "g_local": rec.g_local,
                    "rate_hz": rec.rate_hz,
                    "source": rec.source,
                    "metadata": rec.metadata,
                },
                indent=2,
            )
        )
        print(f"wrote {args.out}")
    if args.poses:
        init = None
        if args.init_static:
            init = int(np.searchsorted(rec.t, args.init_static))
        det = detect_static(rec.accel, window=args.window, multiplier=args.multiplier, init_samples=init)
        means = static_pose_means(rec.t, rec.gyro, rec.accel, det.intervals)
        means.to_csv(args.poses, index=False)
        print(
            f"{len(det)} static poses (threshold {det.threshold:.4g} = {det.multiplier:g} x "
            f"floor {det.noise_floor:.4g} [{det.floor_from}]); wrote {args.poses}"
        )
    return 0
