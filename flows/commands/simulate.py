"""`mimucal simulate OUT --lots L --units N --reps R --seed S`: write a simulated fleet."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

from flows.cli import CliError


def register(sub) -> None:
    p = sub.add_parser(
        "simulate",
        help="write a simulated fleet in the acquisition format (+ fleet.json truth)",
        description="Simulate LOTS x UNITS x REPS turntable sessions (xu2016 multirate + "
        "multiposition + zhang2017 dynamic protocol) and write them under OUT as "
        "lot=*/unit=*/rep=*/{steps,samples}.parquet, with OUT/fleet.json listing "
        "every unit's truth, the injected outliers and the sessions made bad.",
    )
    p.add_argument("out", type=Path, metavar="OUT", help="output dataset root")
    p.add_argument("--lots", type=int, default=1, help="number of lots (default 1)")
    p.add_argument("--units", type=int, default=4, help="units per lot (default 4)")
    p.add_argument(
        "--reps",
        type=int,
        default=None,
        help="repetitions per unit (default 5; with --chamber: sweeps, default 2)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--rate", type=float, default=100.0, metavar="HZ", help="sample rate in Hz (default 100)")
    p.add_argument(
        "--outliers",
        type=int,
        default=0,
        metavar="K",
        help="units with one parameter shifted far beyond the lot spread",
    )
    p.add_argument(
        "--bad-sessions",
        type=int,
        default=0,
        metavar="K",
        help="sessions damaged after writing (NaN burst, truncated file, ...)",
    )
    p.add_argument(
        "--verification",
        action="store_true",
        help="append the xu2016 verification sweep (Table 3) to the protocol",
    )
    p.add_argument(
        "--gyro-unit",
        choices=("deg/s", "rad/s"),
        default=None,
        help="unit of the written gyro samples (default deg/s)",
    )
    p.add_argument(
        "--accel-unit",
        choices=("g", "m/s^2"),
        default=None,
        help="unit of the written accelerometer samples (default g)",
    )
    p.add_argument(
        "--noise-recordings",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="write a static recording of SECONDS per unit (lot=L/unit=U/noise/static.parquet): "
        "the nightly measures each unit's noise model on it (docs/noise.md)",
    )
    p.add_argument(
        "--noisy-units",
        type=int,
        default=0,
        metavar="K",
        help="K units get --noise-factor times the lot's gyro white noise (angle random walk)",
    )
    p.add_argument(
        "--noise-factor",
        type=float,
        default=3.0,
        metavar="N",
        help="with --noisy-units: the factor on their angle random walk (default 3)",
    )
    p.add_argument(
        "--noise-from",
        type=Path,
        default=None,
        metavar="NOISE.json",
        help="the units' noise is this measured model (a 'mimucal noise --json' file): the "
        "recordings' noise, periodic lines and quantization included, and the sessions' white noise",
    )
    p.add_argument(
        "--physics",
        action="store_true",
        help="simulate with the independent physics simulator (each sensor its own "
        "misaligned axis, noise processes, warm-up ramp; docs/physics-simulator.md)",
    )
    p.add_argument(
        "--hide",
        action="append",
        default=[],
        metavar="EFFECT[:SCALE]",
        help="with --physics: hide a catalogue effect in every unit at SCALE times a "
        "realistic size (default 1); repeatable",
    )
    p.add_argument(
        "--no-tilted",
        action="store_true",
        help="with --physics: leave out the dynamic steps on the 45-degree diagonals",
    )
    p.add_argument(
        "--latitude",
        type=float,
        default=None,
        metavar="DEG",
        help="with --physics: add the Earth rate at this latitude",
    )
    p.add_argument(
        "--back-to-back",
        action="store_true",
        help="with --physics: run each unit's repetitions one after the other on one "
        "warm-up (each at its own temperature) instead of a cold start a day",
    )
    p.add_argument(
        "--chamber",
        action="store_true",
        help="with --physics: thermal chamber runs (7 setpoints -40..85 degC, --reps "
        "alternating heating/cooling sweeps, default 2; samples metadata chamber_setpoint_c; "
        "docs/thermal.md)",
    )
    p.add_argument(
        "--out-of-limit",
        type=int,
        default=0,
        metavar="K",
        help="with --chamber: K units (the first of a lot) get a gyro bias coefficient of 0.02 deg/s/degC",
    )
    p.add_argument(
        "--declare-location",
        action="store_true",
        help="with --latitude: write latitude_deg/table_heading_deg into the metadata",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace a fleet simulated earlier in OUT (its lot=* directories and "
        "fleet.json are removed first; a dataset without fleet.json is never "
        "removed)",
    )
    p.set_defaults(func=run)


def run(args) -> int:
    from flows.fleet_sim import MANIFEST, simulate_fleet

    if args.reps is None:
        args.reps = 2 if args.chamber else 5
    for name in ("lots", "units", "reps"):
        if getattr(args, name) < 1:
            raise CliError(f"--{name} must be >= 1")
    if args.rate <= 0:
        raise CliError("--rate must be > 0")
    out: Path = args.out
    if out.exists() and not out.is_dir():
        raise CliError(f"{out} exists and is not a directory")
    if out.is_dir():
        lots = [p for p in out.iterdir() if p.name.startswith("lot=")]
        simulated = (out / MANIFEST).exists()
        if (lots or simulated) and not args.force:
            raise CliError(
                f"{out} already holds a dataset; use --force to replace a simulated "
                f"fleet or choose an empty directory"
            )
        if lots and not simulated:
            raise CliError(
                f"{out} holds a dataset that was not simulated (no {MANIFEST}); refusing to remove it"
            )
        for p in lots:  # a simulated fleet, replaced on request (no stale sessions left)
            shutil.rmtree(p)
        (out / MANIFEST).unlink(missing_ok=True)
    start = time.perf_counter()
    if (args.chamber or args.physics) and (args.noise_recordings or args.noisy_units or args.noise_from):
        raise CliError(
            "--noise-recordings, --noisy-units and --noise-from are options of the fast "
            "simulator, not --physics"
        )
    if args.chamber:
        return _run_chamber(args, out, start)
    if args.physics:
        return _run_physics(args, out, start)
    if args.hide or args.no_tilted or args.latitude is not None or args.declare_location or args.back_to_back:
        raise CliError(
            "--hide, --no-tilted, --latitude, --declare-location and --back-to-back need --physics"
        )
    if args.noise_recordings < 0 or args.noisy_units < 0:
        raise CliError("--noise-recordings and --noisy-units must be >= 0")
    noise_from = _read_noise_json(args.noise_from) if args.noise_from is not None else None
    try:
        manifest = simulate_fleet(
            out,
            args.lots,
            args.units,
            args.reps,
            args.seed,
            sample_rate_hz=args.rate,
            outliers=args.outliers,
            bad_sessions=args.bad_sessions,
            verification=args.verification,
            gyro_unit=args.gyro_unit,
            accel_unit=args.accel_unit,
            noise_recording_s=args.noise_recordings,
            noisy_units=args.noisy_units,
            noise_factor=args.noise_factor,
            noise_from=noise_from,
        )
    except ValueError as exc:
        raise CliError(str(exc)) from None
    elapsed = time.perf_counter() - start
    n = args.lots * args.units * args.reps
    print(
        f"wrote {n} sessions ({args.lots} lot(s) x {args.units} unit(s) x {args.reps} rep(s), "
        f"{manifest['n_steps']} steps at {args.rate:g} Hz, gyro {manifest['file_units']['gyro']}, "
        f"accel {manifest['file_units']['accel']}) to {out} in {elapsed:.1f} s"
    )
    for o in manifest["outliers"]:
        print(f"  outlier: lot={o['lot']}/unit={o['unit']} ({o['param']} {o['shift']:+g})")
    for b in manifest["bad_sessions"]:
        print(f"  bad session: {b['session']} ({b['kind']}: expect {b['expected_code']})")
    if args.noise_recordings:
        print(f"  noise recordings: {args.noise_recordings:g} s per unit (lot=L/unit=U/noise/static.parquet)")
    for u in manifest["noise"]["noisy_units"]:
        print(f"  noisy unit: lot={u['lot']}/unit={u['unit']} ({u['factor']:g}x the angle random walk)")
    print(f"  truth: {out / MANIFEST}")
    return 0


def _read_noise_json(path: Path) -> dict:
    """A ``mimucal noise --json`` document, or a one-line error naming the file."""
    import json

    try:
        doc = json.loads(path.read_text())
    except OSError as exc:
        raise CliError(f"--noise-from {path}: {exc.strerror}") from None
    except ValueError as exc:
        raise CliError(f"--noise-from {path}: not JSON ({exc})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("channels"), dict):
        raise CliError(f"--noise-from {path}: not a 'mimucal noise --json' document (no 'channels')")
    doc.setdefault("source", str(path))
    return doc


def _parse_hide(specs: list[str]) -> tuple[tuple[str, float], ...]:
    from calib_core.effects import catalogue

    out = []
    for spec in specs:
        name, _, scale = spec.partition(":")
        if name not in catalogue():
            raise CliError(f"--hide {spec}: unknown effect {name!r}; known: {', '.join(sorted(catalogue()))}")
        try:
            value = float(scale) if scale else 1.0
        except ValueError:
            raise CliError(f"--hide {spec}: scale {scale!r} is not a number") from None
        out.append((name, value))
    return tuple(out)


def _run_chamber(args, out: Path, start: float) -> int:
    from flows.chamber_sim import simulate_chamber_fleet

    if not args.physics:
        raise CliError("--chamber needs --physics")
    reps = args.reps
    rate = args.rate if args.rate != 100.0 else 50.0
    doc = simulate_chamber_fleet(out, args.lots, args.units, args.seed, reps, rate, args.out_of_limit)
    n = len(doc["units"]) * reps * len(doc["setpoints_c"])
    print(
        f"wrote {n} chamber sessions ({args.lots} lot(s) x {args.units} unit(s), "
        f"{len(doc['setpoints_c'])} setpoints x {reps} sweep(s), {rate:g} Hz) to {out} in "
        f"{time.perf_counter() - start:.1f} s"
    )
    for u in doc["units"]:
        if u["out_of_limit"]:
            print(f"  out of limit: lot={u['lot']}/unit={u['unit']} (gyro x bias 0.02 deg/s/degC)")
    print(f"  truth: {out / 'fleet.json'}")
    return 0


def _run_physics(args, out: Path, start: float) -> int:
    from flows.fleet_sim import MANIFEST, simulate_physics_fleet

    if args.outliers or args.bad_sessions or args.verification or args.gyro_unit or args.accel_unit:
        raise CliError(
            "--physics takes --lots/--units/--reps/--seed/--rate/--hide/--no-tilted/"
            "--latitude/--declare-location/--back-to-back only"
        )
    hide = _parse_hide(args.hide)
    rate = args.rate if args.rate != 100.0 else 50.0  # the physics units' noise is set at 50 Hz
    manifest = simulate_physics_fleet(
        out,
        args.lots,
        args.units,
        args.reps,
        args.seed,
        sample_rate_hz=rate,
        hide=hide,
        tilted=not args.no_tilted,
        latitude_deg=args.latitude,
        declare_location=args.declare_location,
        back_to_back=args.back_to_back,
    )
    n = args.lots * args.units * args.reps
    hidden = ", ".join(f"{h['effect']} x{h['scale']:g}" for h in manifest["hidden"]) or "none"
    print(
        f"wrote {n} physics-simulator sessions ({args.lots} lot(s) x {args.units} unit(s) x "
        f"{args.reps} rep(s), {manifest['n_steps']} steps at {rate:g} Hz; hidden: {hidden}) "
        f"to {out} in {time.perf_counter() - start:.1f} s"
    )
    print(f"  truth: {out / MANIFEST}")
    return 0
