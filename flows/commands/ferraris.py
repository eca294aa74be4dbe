"""`mimucal ferraris CSV --sections SECTIONS.json --rate HZ --out CALIBRATION.json`:
Ferraris calibration (six static poses + three full turns, imucal's method)."""

from __future__ import annotations

from pathlib import Path

from flows.cli import CliError
from flows.commands.import_raw import (
    ACCEL_UNIT_CHOICES,
    GYRO_UNIT_CHOICES,
    add_table_options,
    read_table_args,
)

IMUCAL_MAPPING = "gx=gyr_x,gy=gyr_y,gz=gyr_z,ax=acc_x,ay=acc_y,az=acc_z"


def register(sub) -> None:
    p = sub.add_parser(
        "ferraris",
        help="Ferraris calibration from a hand-made session and its section list",
        description="Compute a Ferraris calibration (Ferraris et al. 1995, as imucal does) from "
        "CSV and the section list SECTIONS (imucal's JSON {name: {start, end}} or "
        "CSV; sample indices, end exclusive) and write CALIBRATION.json "
        "(kind=ferraris; gyro g-sensitivity as the gyro_g_sensitivity term).",
    )
    p.add_argument("csv", type=Path, metavar="CSV")
    p.add_argument("--sections", type=Path, required=True, metavar="SECTIONS")
    add_table_options(p, default_columns=IMUCAL_MAPPING)
    p.add_argument(
        "--gyro-unit",
        choices=GYRO_UNIT_CHOICES,
        default="deg/s",
        help="raw gyro unit of the file (default deg/s)",
    )
    p.add_argument(
        "--accel-unit",
        choices=ACCEL_UNIT_CHOICES,
        default="m/s^2",
        help="raw accel unit of the file (default m/s^2, converted to g with --g)",
    )
    p.add_argument(
        "--g",
        type=float,
        default=9.81,
        metavar="M_S2",
        help="gravity for m/s^2 <-> g (default 9.81, imucal's value)",
    )
    p.add_argument(
        "--expected-angle",
        type=float,
        default=-360.0,
        metavar="DEG",
        help="rotation angle of each turn (default -360: clockwise, imucal's default)",
    )
    p.add_argument("--out", type=Path, required=True, metavar="CALIBRATION.json")
    p.set_defaults(func=run)


def run(args) -> int:
    from calib_core.errors import DesignError
    from calib_core.models.ferraris import ferraris_calibration
    from schemas.calibration_file import save_calibration
    from schemas.errors import SessionError
    from schemas.importers import read_section_list

    if args.rate is None:
        raise CliError("--rate is required (the rotations are integrated with it)")
    rec = read_table_args(args, args.csv, args.gyro_unit, args.accel_unit, args.g)
    try:
        sections = read_section_list(args.sections)
    except SessionError as exc:
        raise CliError(str(exc)) from exc
    try:
        fit = ferraris_calibration(
            rec.gyro,
            rec.accel,
            sections,
            args.rate,
            expected_angle_deg=args.expected_angle,
            gyro_unit=rec.gyro_unit,
            accel_unit=rec.accel_unit,
            g_local=args.g,
            metadata={"source": rec.source},
        )
    except DesignError as exc:
        raise CliError(f"{args.csv}: {exc.reason}") from exc
    summary = fit.summary()
    save_calibration(fit.calibration, args.out, extra={"fit": summary})
    print(
        f"Ferraris calibration of {rec.source} ({len(rec)} samples): static |f| error max "
        f"{summary['static_norm_err_max_mg']:.3g} mg, off-axis max "
        f"{summary['static_offaxis_max_mg']:.3g} mg; wrote {args.out}"
    )
    return 0
