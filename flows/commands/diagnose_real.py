"""`mimucal diagnose-real {xsens,ferraris,poses} [--json FILE]`: model discovery on a
recording without turntable references (static poses), with the effect catalogue.

``xsens``: IMU-TK's Xsens recording, calibrated with the field method (IMU-TK's demo
guesses); ``ferraris``: imucal's session, calibrated with Ferraris; ``poses``: any pose table
(``mimucal field ... --poses`` / ``import-raw ... --poses``) with a calibration file.
See docs/real-discovery.md.
"""

from __future__ import annotations

from pathlib import Path

from flows.cli import CliError

DEFAULT_DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "real"


def register(sub) -> None:
    p = sub.add_parser(
        "diagnose-real",
        help="model discovery on a real recording's static poses (no references)",
        description="Calibrate a recording with its own method, then test every catalogue "
        "effect on its static poses (rate 0, |f| = 1 g): F test per sensor block "
        "with Bonferroni, held-out gain leaving blocks of consecutive poses out.",
    )
    p.add_argument(
        "recording",
        choices=("xsens", "ferraris", "poses"),
        help="xsens (IMU-TK, field calibration), ferraris (imucal session), or "
        "poses (your --poses table and --calibration file)",
    )
    p.add_argument(
        "--data",
        type=Path,
        default=DEFAULT_DATA,
        metavar="DIR",
        help=f"directory of the real recordings (default {DEFAULT_DATA})",
    )
    p.add_argument(
        "--poses",
        type=Path,
        default=None,
        metavar="CSV",
        help="pose table (pose, count, t_mid, gx..az, gx_std..az_std); 'poses' only",
    )
    p.add_argument(
        "--calibration",
        type=Path,
        default=None,
        metavar="JSON",
        help="calibration file the poses are tested against; 'poses' only",
    )
    p.add_argument("--alpha", type=float, default=0.01, help="false-alarm rate per recording (default 0.01)")
    p.add_argument(
        "--block-size",
        type=int,
        default=None,
        metavar="N",
        help="consecutive poses left out together in the held-out score (default: "
        "4, or 1 when there are fewer than 12 poses)",
    )
    p.add_argument(
        "--json", type=Path, default=None, metavar="FILE", help="also write the diagnosis as JSON here"
    )
    p.set_defaults(func=run)


def load_recording(name: str, data: Path):
    """(calibration, pose table, label) of a bundled real recording, calibrated with its
    own method."""
    from calib_core.models.ferraris import ferraris_calibration, section_pose_means
    from calib_core.models.field.imu_tk import field_calibration
    from schemas.importers import IMUCAL_RATE_HZ, read_imucal_csv, read_imutk_pair, read_section_list

    if name == "xsens":
        acc, gyro = data / "imu_tk" / "xsens_acc.txt", data / "imu_tk" / "xsens_gyro.txt"
        rec = read_imutk_pair(acc, gyro)
        res = field_calibration(
            rec.t,
            rec.gyro,
            rec.accel,
            rec.g_local,
            init_acc_bias=32768.0,
            init_gyro_scale=1 / 6258,
            init_static_s=50.0,
            gyro_unit=rec.gyro_unit,
            accel_unit=rec.accel_unit,
        )
        return res.calibration, res.pose_means, f"xsens ({rec.source}, field calibration)"
    csv = data / "imucal" / "example_ferraris_session.csv"
    rec = read_imucal_csv(csv)
    sections = read_section_list(data / "imucal" / "example_ferraris_session_list.json")
    fit = ferraris_calibration(
        rec.gyro,
        rec.accel,
        sections,
        IMUCAL_RATE_HZ,
        gyro_unit=rec.gyro_unit,
        accel_unit=rec.accel_unit,
        g_local=rec.g_local,
    )
    return (
        fit.calibration,
        section_pose_means(rec.t, rec.gyro, rec.accel, sections),
        f"ferraris ({rec.source}, Ferraris calibration)",
    )


def summary_lines(diag) -> list[str]:
    lines = [
        f"{diag.recording}: {diag.n_poses} static poses, false-alarm rate {diag.alpha:g}, "
        f"held out {diag.block_size} consecutive pose(s) at a time"
    ]
    for b, s in diag.blocks.items():
        what = "rate at rest" if b == "gyro" else "|f| - 1 g"
        head = (
            f"  {b} ({what}): baseline rms {s['baseline_rms']:.3g} {s['unit']}, "
            f"white noise of a pose mean {s['white_noise_rms']:.3g}; "
        )
        if s["dof_after"] <= 0:
            lines.append(
                head + "0 dof: the calibration's own parameters fit these poses exactly, nothing to test"
            )
            continue
        lines.append(
            head + f"held-out rms {s['heldout_rms_before']:.3g} -> "
            f"{s['heldout_rms_after']:.3g} {s['unit']} ({s['rms_over_white_before']:.3g}"
            f" -> {s['rms_over_white_after']:.3g} x white, {s['dof_after']} dof)"
        )
    if diag.effects:
        lines.append("effects found:")
    for e in diag.effects:
        ev = e.evidence
        lines.append(
            f"  {e.name} ({e.block}) on {','.join(e.axes)}: F={ev.statistic:.3g} "
            f"({ev.dof1}, {ev.dof2}), p={ev.p_value:.2g} (threshold "
            f"{ev.threshold:.2g}); held-out rms {e.heldout_rms_before:.3g} -> "
            f"{e.heldout_rms_after:.3g} (gain {e.gain:.3g})"
        )
        for n, v in e.estimate.items():
            lines.append(f"      {n} = {v:.4g} +/- {e.stderr[n]:.2g} {e.units[n]}")
    tested = {(c.name, c.block) for c in diag.effects}
    for c in diag.candidates:
        if (c.name, c.block) not in tested:
            ev = c.evidence
            lines.append(
                f"  not significant: {c.name} ({c.block}) F={ev.statistic:.3g} "
                f"({ev.dof1}, {ev.dof2}), p={ev.p_value:.2g}; held-out gain "
                f"{c.gain:.3g}"
            )
    for nt in diag.not_testable:
        lines.append(
            f"  not testable: {nt['name']}"
            + (f" ({nt['block']})" if "block" in nt else "")
            + f": {nt['reason']}"
        )
    for c in diag.baseline_checks:
        ev = c.evidence
        lines.append(
            f"  baseline term {c.name} ({c.block}), tested against dropping it: "
            f"F={ev.statistic:.3g} ({ev.dof1}, {ev.dof2}), p={ev.p_value:.2g}; "
            f"held-out rms {c.heldout_rms_before:.3g} -> {c.heldout_rms_after:.3g} "
            f"(gain {c.gain:.3g})"
        )
    if not diag.effects:
        lines.append("no catalogue effect is significant on this recording")
    if diag.unexplained:
        lines.append(
            "residual still above the white noise of a pose mean (chi2 at alpha/2): "
            "pose-to-pose noise (bias instability, placement) or an effect outside "
            "the catalogue"
        )
    return lines


def run(args) -> int:
    import pandas as pd

    from calib_core.discovery import diagnose_static
    from calib_core.errors import DesignError
    from schemas.calibration_file import load_calibration, write_json_atomic
    from schemas.errors import SessionError

    if not 0 < args.alpha < 1:
        raise CliError(f"--alpha must be between 0 and 1, got {args.alpha}")
    try:
        if args.recording == "poses":
            if args.poses is None or args.calibration is None:
                raise CliError("'poses' needs --poses CSV and --calibration JSON")
            cal = load_calibration(args.calibration)
            poses = pd.read_csv(args.poses)
            label = f"{args.poses.name} against {args.calibration.name}"
        else:
            if not args.data.is_dir():
                raise CliError(f"real recordings not found: {args.data} (give --data DIR)")
            cal, poses, label = load_recording(args.recording, args.data)
    except (SessionError, OSError, ValueError) as exc:
        raise CliError(str(exc)) from exc
    block = args.block_size or (4 if len(poses) >= 12 else 1)
    try:
        diag = diagnose_static(cal, poses, label, alpha=args.alpha, block_size=block)
    except (DesignError, ValueError) as exc:
        raise CliError(f"{label}: {getattr(exc, 'reason', exc)}") from exc
    print("\n".join(summary_lines(diag)))
    if args.json:
        write_json_atomic(args.json, diag.to_dict())
        print(f"-> {args.json}")
    return 0
