"""`mimucal field FILE... --out CALIBRATION.json`: reference-free calibration of a recording
moved by hand through static poses (accelerometer from |f| at the poses, gyro from the
gravity direction across the moves), with before/after and held-out figures of merit."""

from __future__ import annotations

import math
from pathlib import Path

from flows.cli import CliError
from flows.commands.import_raw import (
    ACCEL_UNIT_CHOICES,
    GYRO_UNIT_CHOICES,
    add_table_options,
    number,
    read_table_args,
)


def register(sub) -> None:
    p = sub.add_parser(
        "field",
        help="reference-free calibration from static poses moved by hand",
        description="Calibrate accelerometer (scale, misalignment, bias) and gyro (scale, "
        "misalignment incl. gyro-to-accel, bias from every quiet pose, optional "
        "drift and g-sensitivity) without any reference. Input: IMU-TK's two files "
        "ACC GYRO (t x y z per line), or one CSV/whitespace log (preamble, comments "
        "and header are recognised; --columns unless the header names "
        "ax,ay,az,gx,gy,gz).",
    )
    p.add_argument(
        "files",
        type=Path,
        nargs="+",
        metavar="FILE",
        help="ACC.txt GYRO.txt (IMU-TK), or one CSV/whitespace log",
    )
    add_table_options(p)
    p.add_argument(
        "--gyro-unit", choices=GYRO_UNIT_CHOICES, default="LSB", help="raw gyro unit (default LSB)"
    )
    p.add_argument(
        "--accel-unit", choices=ACCEL_UNIT_CHOICES, default="LSB", help="raw accel unit (default LSB)"
    )
    p.add_argument(
        "--g-local",
        type=float,
        default=9.80665,
        metavar="M_S2",
        help="local gravity magnitude (default 9.80665)",
    )
    p.add_argument(
        "--accel-range",
        default=None,
        metavar="RANGE",
        help="accelerometer full scale of an int16 output, e.g. 2g: starting scale range/32768 per count",
    )
    p.add_argument(
        "--gyro-range",
        default=None,
        metavar="RANGE",
        help="gyro full scale of an int16 output, e.g. 250dps: starting scale "
        "range/32768 per count; samples at +/-32767 count as clipped",
    )
    p.add_argument(
        "--init-static",
        type=float,
        default=None,
        metavar="S",
        help="the recording starts with S seconds at rest: noise floors from it "
        "(default: the preamble's 'Initialization time' if any, else the "
        "quietest 5%% of windows)",
    )
    p.add_argument(
        "--acc-bias",
        type=number,
        default=None,
        metavar="B",
        help="starting accel bias, raw units (default: centre of the static poses)",
    )
    p.add_argument(
        "--acc-scale",
        type=number,
        default=None,
        metavar="S",
        help="starting accel scale, m/s^2 per raw unit (overrides --accel-range)",
    )
    p.add_argument(
        "--gyro-scale",
        type=number,
        default=None,
        metavar="S",
        help="starting gyro scale, rad/s per raw unit, e.g. 1/6258 (overrides "
        "--gyro-range; default: coarse search over an isotropic scale)",
    )
    p.add_argument(
        "--window",
        type=float,
        default=0.25,
        metavar="S",
        help="static detector window in seconds (default 0.25)",
    )
    p.add_argument(
        "--min-pose",
        type=float,
        default=1.0,
        metavar="S",
        help="shortest static pose accepted, seconds (default 1)",
    )
    p.add_argument(
        "--multiplier",
        type=float,
        default=3.0,
        help="static threshold = multiplier x noise floor (default 3)",
    )
    p.add_argument(
        "--drift",
        choices=("auto", "on", "off"),
        default="auto",
        help="gyro bias drift over the recording (default auto: kept when the data show it)",
    )
    p.add_argument(
        "--gyro-g-sensitivity",
        nargs="?",
        choices=("auto", "on", "off"),
        const="on",
        default="auto",
        help="gyro bias linear in specific force (default auto)",
    )
    p.add_argument(
        "--misalignment-prior",
        type=float,
        default=0.01,
        metavar="RAD",
        help="sigma of the datasheet prior on every misalignment (default 0.01 rad: "
        "half a +/-2%% cross-axis limit); 0 switches it off",
    )
    p.add_argument(
        "--folds",
        type=int,
        default=None,
        metavar="N",
        help="held-out folds (default: leave-one-out up to 15 poses, else 5)",
    )
    p.add_argument(
        "--no-held-out", action="store_true", help="skip the held-out figures (one refit per fold)"
    )
    p.add_argument(
        "--method",
        choices=("hand-held", "imu-tk"),
        default="hand-held",
        help="hand-held (default) or imu-tk: IMU-TK's own procedure (bias from the "
        "initial rest, threshold scan, 100 central samples per pose), for "
        "comparison",
    )
    p.add_argument(
        "--poses", type=Path, default=None, metavar="CSV", help="also write the static poses' raw means here"
    )
    p.add_argument("--out", type=Path, required=True, metavar="CALIBRATION.json")
    p.set_defaults(func=run)


def _read(args):
    from schemas.errors import SessionError
    from schemas.importers import read_imutk_pair

    if len(args.files) == 2 and not args.columns:
        try:
            return read_imutk_pair(
                args.files[0], args.files[1], args.gyro_unit, args.accel_unit, args.g_local
            )
        except SessionError as exc:
            raise CliError(str(exc)) from exc
    if len(args.files) == 1:
        return read_table_args(args, args.files[0], args.gyro_unit, args.accel_unit, args.g_local)
    raise CliError("give ACC GYRO (IMU-TK text files) or one log file")


def _check_options(args) -> None:
    """The options as the nightly checks a unit's ``field.json`` (finite, in range, known
    words, one column per channel): one line naming the option."""
    from schemas.field_dataset import FIELD_OPTIONS, option_problem

    for name in FIELD_OPTIONS:
        value = getattr(args, name, None)
        why = option_problem(name, value) if value is not None else None
        if why:
            raise CliError(f"--{name.replace('_', '-')} {why}")


def _refuse_implausible(rec, cal, figures: dict) -> None:
    """No calibration of a sensor that cannot be is written: ``E_IMPLAUSIBLE`` (exit 2) when
    the fit fails :func:`calib_core.guards.check_field_fit`."""
    from calib_core.guards import check_field_fit

    bad = check_field_fit(
        figures.get("after_norm_rms_mg", float("nan")),
        figures.get("after_angle_rms_deg", float("nan")),
        cal.K_g,
        cal.w0,
        cal.K_a,
        cal.f0,
    )
    if bad:
        raise CliError(
            f"{rec.source}: [E_IMPLAUSIBLE] estimates are not those of a working sensor: "
            + "; ".join(map(str, bad))
            + "; check --g-local, the scales and --columns; no calibration written"
        )


def _init_static(args, rec) -> float | None:
    from schemas.field_options import init_static_s

    return init_static_s(vars(args), rec.metadata.get("preamble", {}))


def _starting_scales(args, rec) -> tuple[float | None, float | None]:
    from schemas.field_options import starting_scales

    try:
        return starting_scales(vars(args), rec.gyro_unit, rec.accel_unit)
    except ValueError as exc:
        raise CliError(str(exc)) from exc


def run(args) -> int:
    import numpy as np

    from calib_core.errors import DesignError
    from calib_core.models.field.joint import Priors, field_figures, fit_field, held_out_figures, usable_moves
    from calib_core.models.field.static_detection import clipped_samples, detect_poses
    from schemas.calibration_file import save_calibration
    from schemas.field_options import clip_limit

    _check_options(args)
    rec = _read(args)
    init_s = _init_static(args, rec)
    acc_scale, gyro_scale = _starting_scales(args, rec)
    try:
        det = detect_poses(
            rec.t,
            rec.gyro,
            rec.accel,
            init_s=init_s,
            window_s=args.window,
            min_pose_s=args.min_pose,
            multiplier=args.multiplier,
        )
    except ValueError as exc:
        raise CliError(f"{rec.source}: {exc}") from exc
    clipped = clipped_samples(rec.gyro, clip_limit(vars(args)))
    move_ok = usable_moves(rec.gyro, det.poses, clipped)
    on_off = {"auto": "auto", "on": True, "off": False}
    kwargs = {
        "accel_scale": acc_scale,
        "gyro_scale": gyro_scale,
        "accel_bias": args.acc_bias,
        "drift": on_off[args.drift],
        "g_sensitivity": on_off[args.gyro_g_sensitivity],
        "priors": Priors(args.misalignment_prior or None),
    }
    try:
        if args.method == "imu-tk":
            cal, params, stderr, model = _imu_tk(args, rec, init_s)
        else:
            fit = fit_field(
                rec.t,
                rec.gyro,
                rec.accel,
                det.poses,
                rec.g_local,
                move_use=move_ok,
                gyro_unit=rec.gyro_unit,
                accel_unit=rec.accel_unit,
                metadata={"source": rec.source},
                **kwargs,
            )
            cal, params, stderr = fit.calibration, fit.params(), fit.stderrs()
            model = {
                "gyro_bias_drift": fit.gyro.drift,
                "gyro_g_sensitivity": fit.gyro.g_sensitivity,
                "wald": {k: list(v) for k, v in fit.gyro.wald.items()},
            }
        before = (
            None
            if args.method == "imu-tk"
            else field_figures(fit.start, rec.t, rec.gyro, rec.accel, det.poses)
        )
        after = field_figures(cal, rec.t, rec.gyro, rec.accel, det.poses)
        held = None
        if not args.no_held_out and args.method != "imu-tk":
            held = held_out_figures(
                rec.t,
                rec.gyro,
                rec.accel,
                det.poses,
                rec.g_local,
                move_ok=move_ok,
                n_folds=args.folds,
                **kwargs,
            )
    except DesignError as exc:
        raise CliError(f"{rec.source}: {exc.reason}") from exc
    figures = {**after.summary("after_", move_ok)}
    _refuse_implausible(rec, cal, figures)
    if before is not None:
        figures.update(before.summary("before_", move_ok))
    if held is not None:
        figures.update(held.summary())
    t = rec.t
    poses_doc = {
        "used": [
            {"start_s": float(t[p.start]), "end_s": float(t[p.end - 1]), "gyro_quiet": p.gyro_quiet}
            for p in det.poses
        ],
        "rejected": [
            {"start_s": float(t[r.start]), "end_s": float(t[r.end - 1]), "reason": r.reason}
            for r in det.rejected
        ],
        "moves_unusable": [int(j) for j in np.flatnonzero(~move_ok)],
        "detector": {
            "window": det.window,
            "min_samples": det.min_samples,
            "rate_hz": det.rate_hz,
            "multiplier": det.multiplier,
            "floor_from": det.floor_from,
            "accel_floor": det.accel_floor,
            "gyro_floor": det.gyro_floor,
        },
    }
    save_calibration(
        cal,
        args.out,
        extra={
            "fit": {
                "figures": _json_numbers(figures),
                "model": model,
                "params": params,
                "stderr": _json_numbers(stderr),
            },
            "poses": poses_doc,
        },
    )
    if args.poses:
        from calib_core.models.field.static_detection import static_pose_means

        static_pose_means(rec.t, rec.gyro, rec.accel, det.intervals()).to_csv(args.poses, index=False)
    _print_summary(args, rec, det, move_ok, figures, model, held)
    return 0


def _json_numbers(d: dict) -> dict:
    """Non-finite figures (a fold that could not be fitted) are written as null."""
    return {k: (v if not isinstance(v, float) or math.isfinite(v) else None) for k, v in d.items()}


def _imu_tk(args, rec, init_s):
    from calib_core.models.field.imu_tk import field_calibration

    res = field_calibration(
        rec.t,
        rec.gyro,
        rec.accel,
        rec.g_local,
        init_static_s=init_s or 50.0,
        init_acc_bias=args.acc_bias,
        init_acc_scale=args.acc_scale,
        init_gyro_scale=args.gyro_scale,
        gyro_unit=rec.gyro_unit,
        accel_unit=rec.accel_unit,
        gyro_g_sensitivity=args.gyro_g_sensitivity == "on",
        metadata={"source": rec.source},
    )
    return res.calibration, res.params(), {}, {"method": "imu-tk"}


def _print_summary(args, rec, det, move_ok, f, model, held) -> None:
    n_quiet = sum(p.gyro_quiet for p in det.poses)
    print(
        f"field calibration of {rec.source} ({args.method}): {len(det.poses)} static poses used "
        f"({n_quiet} with the gyro at rest), {len(det.rejected)} rejected; "
        f"{int(move_ok.sum())} of {len(move_ok)} moves used"
        + (f" ({int((~move_ok).sum())} with a clipped gyro sample)" if (~move_ok).any() else "")
    )
    for r in det.rejected:
        print(f"  rejected pose {rec.t[r.start]:.2f}-{rec.t[r.end - 1]:.2f} s: {r.reason}")

    def fmt(key):
        v = f.get(key)
        return "n/a" if v is None or not math.isfinite(v) else f"{v:.3g}"

    held_txt = ""
    if held is not None:
        held_txt = (
            f"; held out ({held.pose_folds} folds over poses, {held.move_folds} over moves): "
            f"{fmt('held_out_norm_rms_mg')} mg, {fmt('held_out_angle_rms_deg')} deg"
        )
    print(
        f"  static |f| error, RMS over poses: {fmt('before_norm_rms_mg')} -> "
        f"{fmt('after_norm_rms_mg')} mg; gravity direction across moves, RMS: "
        f"{fmt('before_angle_rms_deg')} -> {fmt('after_angle_rms_deg')} deg{held_txt}"
    )
    if "gyro_bias_drift" in model:
        print(
            f"  gyro model: bias drift {'kept' if model['gyro_bias_drift'] else 'not kept'}, "
            f"g-sensitivity {'kept' if model['gyro_g_sensitivity'] else 'not kept'}"
        )
    print(f"wrote {args.out}")
    if args.poses:
        print(f"wrote {args.poses}")
