"""`mimucal noise RECORDING`: Allan deviation, the fitted noise model (IEEE 952/1293
coefficients with intervals, periodic lines, goodness of fit) of a static recording, as a
table on stdout, a JSON document (--json) and Kalibr's imu.yaml noise figures
(--kalibr-yaml). The numerics are calib_core.noise; reading and writing schemas.noise_recording."""

from __future__ import annotations

from pathlib import Path

from flows.cli import CliError
from flows.commands.import_raw import ACCEL_UNIT_CHOICES, GYRO_UNIT_CHOICES, add_table_options


def register(sub) -> None:
    p = sub.add_parser(
        "noise",
        help="noise of a static recording: Allan deviation, IEEE coefficients, periodic lines",
        description="Measure the noise of RECORDING (a contract samples.parquet or a CSV/"
        "whitespace log with a header or --columns), recorded at rest: overlapping Allan "
        "deviation with confidence intervals, the composite noise model fitted to the whole "
        "curve with the processes discovery names (quantization, white, bias instability, "
        "random walk, ramp, Gauss-Markov) and their IEEE 952/1293 coefficients with 95%% "
        "intervals, and the periodic lines the spectrum shows in both halves of the record. "
        "See docs/noise.md.",
    )
    p.add_argument("recording", type=Path, metavar="RECORDING")
    add_table_options(p)
    p.add_argument(
        "--gyro-unit",
        choices=GYRO_UNIT_CHOICES,
        default="deg/s",
        help="gyro unit of a text log (default deg/s; raw counts need --gyro-range)",
    )
    p.add_argument(
        "--accel-unit",
        choices=ACCEL_UNIT_CHOICES,
        default="g",
        help="accelerometer unit of a text log (default g; raw counts need --accel-range)",
    )
    p.add_argument("--gyro-range", metavar="RANGE", help="gyro full scale of raw counts, e.g. 250dps")
    p.add_argument("--accel-range", metavar="RANGE", help="accelerometer full scale of raw counts, e.g. 2g")
    p.add_argument(
        "--g-local",
        type=float,
        default=9.80665,
        metavar="M_S2",
        help="gravity for m/s^2 input -> g (default 9.80665)",
    )
    p.add_argument("--json", type=Path, default=None, metavar="FILE", help="write the analysis as JSON")
    p.add_argument(
        "--kalibr-yaml",
        type=Path,
        default=None,
        metavar="FILE",
        help="write Kalibr's imu.yaml noise figures (continuous-time SI)",
    )
    p.set_defaults(func=run)


def _ranges(args) -> tuple[float | None, float | None]:
    from schemas.importers import parse_range

    try:
        g = parse_range(args.gyro_range, "gyro") if args.gyro_range else None
        a = parse_range(args.accel_range, "accel") if args.accel_range else None
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    return g, a


def _fmt(entry: dict | None) -> str:
    if entry is None:
        return "-"
    if entry.get("value") is None:
        if entry.get("hi") is None:
            return "not determined"
        return f"< {entry['hi']:.3g}"
    return f"{entry['value']:.3g} [{entry['lo']:.3g}, {entry['hi']:.3g}]"


def summary_lines(doc: dict) -> list[str]:
    """The human table: one line per channel and coefficient group."""
    from calib_core.noise.model import COEFFICIENTS

    out = [
        f"{doc['n_samples']} samples at {doc['rate_hz']:g} Hz ({doc['duration_s']:.0f} s); "
        "coefficients in IEEE 952/1293 units, 95 % intervals; '< x' = not named, upper bound"
    ]
    for name, ch in doc["channels"].items():
        co = ch["coefficients"]
        parts = [f"{c} {_fmt(co.get(c))} {co[c]['unit']}" for c in COEFFICIENTS if co.get(c)]
        gm = co.get("gauss_markov")
        if gm:
            parts.append(
                f"gauss_markov {gm['value']:.3g} {gm['unit']} (tau {gm['correlation_time_s']:.3g} s)"
            )
        fit = ch["fit"]
        out.append(f"{name} [{ch['unit']}]: " + "; ".join(parts))
        for line in ch["periodic"]:
            out.append(
                f"  line {line['frequency_hz']:.2f} Hz, amplitude {line['amplitude']:.3g} {line['unit']} "
                f"({line['psd_ratio_to_median']:.1f}x the spectrum's median)"
            )
        out.append(
            f"  model: {' + '.join(fit['processes'])}"
            + (" + lines" if ch["periodic"] else "")
            + f"; ADEV within the 95 % intervals at {100 * fit['fraction_within_ci']:.0f} % of "
            f"{len(ch['allan']['tau_s'])} cluster sizes, chi2 {fit['chi2']:.1f} on {fit['dof']} dof"
        )
    k = doc.get("kalibr", {})
    kal = [f"{key} {k[key]:.3g} {k[key + '_unit']}" for key in k if key + "_unit" in k]
    if kal:
        out.append("Kalibr (continuous-time SI, largest axis): " + "; ".join(kal))
    return out


def run(args) -> int:
    from calib_core.noise import analyse_recording
    from schemas.errors import SessionError
    from schemas.importers import parse_column_mapping
    from schemas.noise_recording import (
        NoiseInputError,
        read_static_recording,
        write_kalibr_yaml,
        write_noise_json,
    )

    if args.rate is not None and args.rate <= 0:
        raise CliError("--rate must be > 0")
    gyro_range, accel_range = _ranges(args)
    try:
        mapping = parse_column_mapping(args.columns) if args.columns else None
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    try:
        rec = read_static_recording(
            args.recording,
            mapping,
            args.gyro_unit,
            args.accel_unit,
            args.rate,
            gyro_range,
            accel_range,
            args.g_local,
            args.time_scale,
        )
        analysis = analyse_recording(rec.channels, rec.rate_hz, rec.units, rec.resolution)
    except (SessionError, NoiseInputError) as exc:
        raise CliError(str(exc)) from exc
    except ValueError as exc:
        raise CliError(f"{args.recording}: {exc}") from exc
    doc = analysis.to_dict()
    doc["source"] = rec.source
    for line in summary_lines(doc):
        print(line)
    if args.json:
        write_noise_json(args.json, doc)
        print(f"wrote {args.json}")
    if args.kalibr_yaml:
        write_kalibr_yaml(args.kalibr_yaml, analysis.kalibr(), rec.source)
        print(f"wrote {args.kalibr_yaml}")
    return 0
