"""``mimucal apply CALIBRATION.json RAW OUT``: apply a calibration file to raw samples.

RAW is either a ``samples.parquet`` of the acquisition contract (its metadata gives the raw
units; ``rad/s`` and ``m/s^2`` are converted to deg/s and g first, with the file's
``g_local``) or a CSV with columns ``acc_x, acc_y, acc_z, gyr_x, gyr_y, gyr_z`` (units given by
``--gyro-unit`` / ``--accel-unit``, default deg/s and m/s^2; other columns are passed through).

Output columns: from a Parquet input ``w_x, w_y, w_z`` in deg/s and ``f_x, f_y, f_z`` in g
(plus ``t``, ``step``, ``temp_c`` when present); from a CSV input ``gyr_*`` in deg/s and
``acc_*`` in m/s^2 (the calibration's ``g_local``), other columns unchanged. The output's
format is the one its name says: ``.parquet`` (with the units and the calibration file in its
metadata) or ``.csv``; any other name is refused before anything is read.

Refuses (exit 2) when the raw units of the data are not the ones the calibration expects
(its ``raw_units``), e.g. LSB data with a calibration fitted on deg/s: the result would be
meaningless, so ``--force`` does not override this. Refuses (exit 2) a ``samples.parquet``
whose metadata names another unit than the calibration's (``provenance.unit``), unless
``--force`` (then a warning on stderr); the same for a file whose hive path
(``.../unit=<id>/...``) names another unit. Warns on stderr when the calibration's QA status is
``flagged`` or ``limits``. A thermal calibration (format 1.1) takes each sample's parameters
at its ``temp_c`` and refuses (exit 2, one line) samples without it or outside the calibrated
temperature range, unless ``--extrapolate``."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from flows.cli import CliError

EPILOG = """examples:
  mimucal apply results/calibrations/U0001/20261121T020000.000000Z.json \\
      data/lot=L01/unit=U0001/rep=1/samples.parquet calibrated.parquet
  mimucal apply cal.json recording.csv calibrated.csv --accel-unit m/s^2 --gyro-unit deg/s"""

CSV_GYRO = ("gyr_x", "gyr_y", "gyr_z")
CSV_ACCEL = ("acc_x", "acc_y", "acc_z")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "apply",
        help="apply a calibration file to raw samples (Parquet or CSV)",
        description=__doc__,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("calibration", metavar="CALIBRATION.json")
    p.add_argument("raw", metavar="RAW", help="samples.parquet of the contract, or a .csv")
    p.add_argument("out", metavar="OUT", help="output file: .parquet or .csv (the format its name says)")
    p.add_argument(
        "--gyro-unit",
        default="deg/s",
        choices=("deg/s", "rad/s", "LSB", "V"),
        help="CSV only: unit of gyr_* (default deg/s)",
    )
    p.add_argument(
        "--accel-unit",
        default="m/s^2",
        choices=("g", "m/s^2", "LSB", "V"),
        help="CSV only: unit of acc_* (default m/s^2)",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="apply even if the raw file's hive path or metadata names another unit",
    )
    p.add_argument(
        "--extrapolate",
        action="store_true",
        help="thermal calibration: apply the polynomials to temp_c outside the calibrated range",
    )
    p.set_defaults(func=run)


def _check_unit_id(doc: dict, md: dict, raw: Path, force: bool) -> None:
    """The unit the raw file names, by its hive path (``unit=<id>``, the dataset's key) and by
    its metadata, against the calibration's unit: another unit is refused in one line unless
    ``force`` (then a warning on stderr)."""
    import sys

    from schemas.hive import hive_keys

    cal_unit = (doc.get("provenance") or {}).get("unit") or (doc.get("metadata") or {}).get("unit")
    if not cal_unit:
        return
    named = {"hive path": hive_keys(raw.resolve()).get("unit"), "metadata": md.get("unit")}
    other = {where: str(u) for where, u in named.items() if u and str(u) != str(cal_unit)}
    if not other:
        return
    units = sorted(set(other.values()))
    msg = (
        f"{raw}: the raw file's {' and '.join(other)} name{'s' if len(other) == 1 else ''} unit "
        f"{' / '.join(repr(u) for u in units)}, the calibration is of unit {str(cal_unit)!r}"
    )
    if not force:
        raise CliError(msg + "; pass --force to apply it anyway")
    print(f"mimucal apply: warning: {msg} (--force)", file=sys.stderr)


def _warn_qa(doc: dict, path: str) -> None:
    import sys

    from schemas.calibration_file import qa_of

    qa = qa_of(doc)
    if qa is not None and qa["status"] != "pass":
        print(
            f"mimucal apply: warning: {path} has QA status {qa['status']!r}: "
            + "; ".join(qa.get("reasons") or []),
            file=sys.stderr,
        )


OUTPUT_FORMATS = {".parquet": "Parquet", ".csv": "CSV"}


def write_output(res, out: Path, out_format: str, meta: dict[str, str]) -> None:
    """Write the calibrated samples atomically (temp file + rename) in ``out_format``;
    Parquet keeps ``meta`` (units, calibration file, source) as key-value metadata."""
    import os
    import tempfile

    import pyarrow as pa
    import pyarrow.parquet as pq

    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent)
    os.close(fd)
    try:
        if out_format == "Parquet":
            tab = pa.Table.from_pandas(res, preserve_index=False)
            tab = tab.replace_schema_metadata({**(tab.schema.metadata or {}), **meta})
            pq.write_table(tab, tmp, compression="zstd")
        else:
            res.to_csv(tmp, index=False)
        os.chmod(tmp, 0o644)
        os.replace(tmp, out)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _same_file(a: Path, b: Path) -> bool:
    """Whether ``a`` and ``b`` name one file (the same path, or through links)."""
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return a.resolve() == b.resolve()


def run(args: argparse.Namespace) -> int:
    import pandas as pd
    import pyarrow.parquet as pq

    from schemas.api import CalibrationMismatch, TemperatureOutOfRange, apply_to_frame
    from schemas.calibration_file import (
        CalibrationFileError,
        calibration_from_dict,
        read_calibration_document,
    )
    from schemas.contract import G_LOCAL_DEFAULT, decode_metadata
    from schemas.importers import accel_from_g

    try:
        doc = read_calibration_document(Path(args.calibration))
        cal = calibration_from_dict(doc, source=str(args.calibration))
    except CalibrationFileError as exc:
        raise CliError(str(exc)) from None
    _warn_qa(doc, args.calibration)
    raw, out = Path(args.raw), Path(args.out)
    if _same_file(raw, out):
        raise CliError(
            f"{out}: OUT is the raw input RAW ({raw}); write the calibrated samples to another file"
        )
    out_format = OUTPUT_FORMATS.get(out.suffix.lower())
    if out_format is None:
        raise CliError(f"{out}: output name must end in .parquet or .csv (the format written)")
    if not raw.is_file():
        raise CliError(f"{raw}: no such file")
    suffix = raw.suffix.lower()
    if suffix == ".parquet":
        try:
            table = pq.read_table(raw)
        except Exception as exc:
            raise CliError(f"{raw}: cannot read Parquet ({exc})") from None
        md = decode_metadata(table.schema.metadata)
        missing = [c for c in ("gx", "gy", "gz", "ax", "ay", "az") if c not in table.column_names]
        if missing:
            raise CliError(f"{raw}: missing column(s) {', '.join(missing)} (contract samples.parquet)")
        if "gyro_unit" not in md or "accel_unit" not in md:
            raise CliError(f"{raw}: metadata gyro_unit/accel_unit missing; cannot tell the raw units")
        _check_unit_id(doc, md, raw, args.force)
        df = table.to_pandas()
        df.attrs = {"g_local": float(md.get("g_local", G_LOCAL_DEFAULT))}
        try:  # the unit id was checked above (--force may override it)
            out_cols = apply_to_frame(
                cal, df, md["gyro_unit"], md["accel_unit"], extrapolate=args.extrapolate
            )
        except TemperatureOutOfRange as exc:
            raise CliError(f"{raw}: {exc}") from None
        except CalibrationMismatch as exc:
            raise CliError(
                f"{raw}: {exc}; a calibration only applies to data in the units it was fitted on"
            ) from None
        res = out_cols[
            [c for c in ("step", "t", "temp_c") if c in out_cols]
            + [f"w_{a}" for a in "xyz"]
            + [f"f_{a}" for a in "xyz"]
        ].reset_index(drop=True)
        w = res[[f"w_{a}" for a in "xyz"]].to_numpy()
        meta = {
            "gyro_unit": "deg/s",
            "accel_unit": "g",
            "calibrated": "true",
            "calibration_file": str(Path(args.calibration).resolve()),
            "source": str(raw),
            "g_local": f"{cal.g_local:.5f}",
        }
        units = "w_* deg/s, f_* g"
    elif suffix == ".csv":
        _check_unit_id(doc, {}, raw, args.force)
        try:
            df = pd.read_csv(raw)
        except Exception as exc:
            raise CliError(f"{raw}: cannot read CSV ({exc})") from None
        missing = [c for c in CSV_ACCEL + CSV_GYRO if c not in df]
        if missing:
            raise CliError(
                f"{raw}: missing column(s) {', '.join(missing)} (need {', '.join(CSV_ACCEL + CSV_GYRO)})"
            )
        raw_cols = dict(zip(CSV_GYRO + CSV_ACCEL, ("gx", "gy", "gz", "ax", "ay", "az")))
        samples = df[[c for c in ("t", "temp_c", *raw_cols) if c in df]].rename(columns=raw_cols)
        try:
            out_cols = apply_to_frame(
                cal, samples, args.gyro_unit, args.accel_unit, extrapolate=args.extrapolate
            )
        except TemperatureOutOfRange as exc:
            raise CliError(f"{raw}: {exc}") from None
        except CalibrationMismatch as exc:
            raise CliError(
                f"{raw}: {exc}; a calibration only applies to data in the units it was fitted on"
            ) from None
        w = out_cols[[f"w_{a}" for a in "xyz"]].to_numpy()
        res = df.copy()
        res[list(CSV_GYRO)] = w
        # back to the CSV's m/s^2 with the calibration's g_local (the importers' conversion, inverted)
        res[list(CSV_ACCEL)] = accel_from_g(
            out_cols[[f"f_{a}" for a in "xyz"]].to_numpy(), "m/s^2", cal.g_local
        )
        meta = {
            "gyro_unit": "deg/s",
            "accel_unit": "m/s^2",
            "calibrated": "true",
            "calibration_file": str(Path(args.calibration).resolve()),
            "source": str(raw),
            "g_local": f"{cal.g_local:.5f}",
        }
        units = "gyr_* deg/s, acc_* m/s^2"
    else:
        raise CliError(f"{raw}: expected a .parquet (contract samples) or .csv file")
    write_output(res, out, out_format, meta)
    print(f"{out}: {len(w)} samples calibrated ({units}, {out_format})")
    return 0
