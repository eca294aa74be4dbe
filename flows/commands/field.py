"""`mimucal field ACC.txt GYRO.txt --out CALIBRATION.json`: reference-free multi-position
calibration (Tedaldi, Pretto, Menegatti 2014; IMU-TK) of a recording moved by hand."""
from __future__ import annotations

import json
from pathlib import Path

from flows.cli import CliError
from flows.commands.import_raw import (ACCEL_UNIT_CHOICES, GYRO_UNIT_CHOICES, add_table_options,
                                       number, read_table_args)


def register(sub) -> None:
    p = sub.add_parser(
        "field", help="reference-free calibration from static poses moved by hand (IMU-TK)",
        description="Calibrate accelerometer (scale, misalignment, bias) and gyro (scale, "
                    "misalignment; bias from the initial rest period) without any reference "
                    "(Tedaldi et al. 2014). Input: IMU-TK's two files ACC GYRO (t x y z per "
                    "line), or one table with --columns. The recording must start at rest "
                    "for --init-static seconds.")
    p.add_argument("files", type=Path, nargs="+", metavar="FILE",
                   help="ACC.txt GYRO.txt (IMU-TK), or one CSV/whitespace table with --columns")
    add_table_options(p)
    p.add_argument("--gyro-unit", choices=GYRO_UNIT_CHOICES, default="LSB",
                   help="raw gyro unit (default LSB)")
    p.add_argument("--accel-unit", choices=ACCEL_UNIT_CHOICES, default="LSB",
                   help="raw accel unit (default LSB)")
    p.add_argument("--g-local", type=float, default=9.81744, metavar="M_S2",
                   help="local gravity magnitude (default 9.81744, IMU-TK's demo)")
    p.add_argument("--init-static", type=float, default=50.0, metavar="S",
                   help="initial rest period in s (noise floor, gyro bias; default 50)")
    p.add_argument("--acc-bias", type=number, default=None, metavar="B",
                   help="initial accel bias, raw units (IMU-TK demo: 32768; default: centre "
                        "of the static poses)")
    p.add_argument("--acc-scale", type=number, default=None, metavar="S",
                   help="initial accel scale, m/s^2 per raw unit (default: from the data)")
    p.add_argument("--gyro-scale", type=number, default=None, metavar="S",
                   help="initial gyro scale, rad/s per raw unit, e.g. 1/6258 (IMU-TK demo); "
                        "default: coarse search over an isotropic scale")
    p.add_argument("--window", type=int, default=101, metavar="N",
                   help="static detector window, samples (default 101)")
    p.add_argument("--interval-samples", type=int, default=100, metavar="N",
                   help="central samples used per static pose (default 100)")
    p.add_argument("--min-poses", type=int, default=12, metavar="N",
                   help="fewest static poses accepted (default 12)")
    p.add_argument("--gyro-g-sensitivity", action="store_true",
                   help="also estimate the gyro g-sensitivity (bias linear in specific force) "
                        "from the static poses and store it as the gyro_g_sensitivity term; "
                        "the bias then comes from all poses, not the initial period")
    p.add_argument("--poses", type=Path, default=None, metavar="CSV",
                   help="also write the static poses' raw means here")
    p.add_argument("--out", type=Path, required=True, metavar="CALIBRATION.json")
    p.set_defaults(func=run)


def run(args) -> int:
    from calib_core.errors import DesignError
    from calib_core.field import field_calibration
    from schemas.calibration_file import save_calibration
    from schemas.errors import SessionError
    from schemas.importers import read_imutk_pair

    if len(args.files) == 2 and not args.columns:
        try:
            rec = read_imutk_pair(args.files[0], args.files[1], args.gyro_unit, args.accel_unit,
                                  args.g_local)
        except SessionError as exc:
            raise CliError(str(exc)) from exc
    elif len(args.files) == 1:
        rec = read_table_args(args, args.files[0], args.gyro_unit, args.accel_unit, args.g_local)
    else:
        raise CliError("give ACC GYRO (IMU-TK text files) or one table with --columns")
    try:
        res = field_calibration(rec.t, rec.gyro, rec.accel, rec.g_local,
                                init_static_s=args.init_static, window=args.window,
                                interval_samples=args.interval_samples,
                                min_intervals=args.min_poses, init_acc_bias=args.acc_bias,
                                init_acc_scale=args.acc_scale, init_gyro_scale=args.gyro_scale,
                                gyro_unit=rec.gyro_unit, accel_unit=rec.accel_unit,
                                gyro_g_sensitivity=args.gyro_g_sensitivity,
                                metadata={"source": rec.source})
    except DesignError as exc:
        raise CliError(f"{rec.source}: {exc.reason}") from exc
    stats = {k: float(v) for k, v in res.stats.items()}
    save_calibration(res.calibration, args.out,
                     extra={"fit": stats, "imu_tk_params": res.params()})
    if args.poses:
        res.pose_means.to_csv(args.poses, index=False)
    s = stats
    print(f"field calibration of {rec.source}: {int(s['n_static_poses'])} static poses "
          f"(threshold x{int(s['threshold_multiplier'])}); static |f| RMS error "
          f"{s['accel_norm_rms_err_mg_initial']:.3g} -> {s['accel_norm_rms_err_mg']:.3g} mg; "
          f"gravity direction after rotation, median {s['gyro_angle_median_deg_initial']:.3g} -> "
          f"{s['gyro_angle_median_deg']:.3g} deg; rate at the poses "
          f"{s['gyro_static_rate_rms_dps']:.3g} deg/s RMS; wrote {args.out}")
    if args.poses:
        print(f"wrote {args.poses}")
    return 0
