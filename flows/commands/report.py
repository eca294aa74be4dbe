"""``mimucal report --results DIR --lot LOT``: rebuild a lot's flags and report from the
results store (no raw data is read)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from flows.cli import CliError
from flows.commands.nightly import CONFIG_HELP, check_config

EPILOG = """examples:
  mimucal report --results results --lot L01
  mimucal report --results results --lot L01 --config limits.toml
  mimucal report --results results --lot L01 --config none   # forget the stored limits
  mimucal report --results results --lot L01 --pdf            # results/reports/L01.pdf
  mimucal report --results results --lot L01 --pdf L01-2026-11.pdf

--pdf prints the lot report with Debian's chromium (headless --print-to-pdf): the summary,
every model's key-parameter table, the lot figures and the sessions; unit sections folded."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "report",
        help="rebuild one lot's outlier flags and HTML report",
        description=__doc__,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--results", required=True, metavar="DIR", help="results store directory")
    p.add_argument("--lot", required=True, help="lot id")
    p.add_argument("--config", metavar="TOML", default=None, help=CONFIG_HELP)
    p.add_argument("--wait", action="store_true", help="wait for a run holding the store")
    p.add_argument(
        "--pdf",
        nargs="?",
        const="",
        default=None,
        metavar="FILE",
        help="also print the lot report to PDF (default RESULTS/reports/<lot>.pdf)",
    )
    p.add_argument(
        "--verbose",
        action="store_true",
        help="show Prefect's log lines on the terminal (default: RESULTS/logs/prefect.log)",
    )
    p.set_defaults(func=run)


def check_pdf_path(pdf: Path, results: Path, lot: str) -> None:
    """A ``--pdf FILE`` inside the results store is refused (it would overwrite a table, a
    calibration or the lock), except the default ``reports/<lot>.pdf`` itself."""
    from reports.lot import lot_report_path

    target, root = pdf.resolve(), results.resolve()
    if target == lot_report_path(results, lot).with_suffix(".pdf").resolve():
        return
    if target == root or target.is_relative_to(root):
        raise CliError(
            f"--pdf {pdf}: inside the results store {root}, whose files are the tool's own; "
            "write the PDF elsewhere, or omit FILE for reports/<lot>.pdf"
        )


def run(args: argparse.Namespace) -> int:
    check_config(args.config)
    from flows.user_errors import check_lot

    check_lot(args.results, args.lot)  # answered before Prefect starts, with the lots there are
    if args.pdf:
        check_pdf_path(Path(args.pdf), Path(args.results), args.lot)
    if args.pdf is not None:
        from reports.pdf import PdfError, chromium_or_error

        try:
            chromium_or_error()  # before the report is rebuilt, not after
        except PdfError as exc:
            raise CliError(str(exc)) from None
    from flows import runtime

    runtime.ensure_environment(args.results, verbose=args.verbose)
    runtime.start_api_server_early()  # while the flow's modules are imported
    from calib_core.outliers import OutlierConfigError
    from flows import nightly
    from schemas.results_store import StoreLockedError

    try:
        out = nightly.lot_quality_report(args.results, args.lot, args.config, args.wait)
    except (StoreLockedError, OutlierConfigError, FileNotFoundError, LookupError) as exc:
        raise CliError(str(exc)) from None
    for lf in out["flags"]:
        print(lf["note"])
        for f in lf["flags"]:
            print(f"flag {f['lot']}/{f['unit']}: [{f['kind']}] {f['reason']}")
    for p in out["problems"]:
        print(f"report: {p}", file=sys.stderr)
    for r in out["reports"]:
        print(r)
    if args.pdf is not None:
        from reports.lot import lot_report_path
        from reports.pdf import PdfError, print_pdf

        html = lot_report_path(args.results, args.lot)
        pdf = Path(args.pdf) if args.pdf else html.with_suffix(".pdf")
        try:
            print(print_pdf(html, pdf))
        except PdfError as exc:
            raise CliError(str(exc)) from None
    return 1 if out["problems"] else 0
