"""A report as PDF, for the archive: Debian's chromium prints the HTML file headless
(``--print-to-pdf``). The page's print style shows every model's key-parameter table (not
only the chosen tab), unfolds the scrolling tables and leaves the buttons out; the figures are
drawn before printing (``--virtual-time-budget`` lets the page's scripts run first). Unit
sections stay folded: a lot's PDF is its summary, tables and lot figures.

``python -m reports.pdf REPORT.html OUT.pdf``.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

from reports.browser import FLAGS, find_chromium

SCRIPT_BUDGET_MS = 20000  # virtual time for the page's scripts (figures) before printing


class PdfError(RuntimeError):
    """The PDF could not be printed (no chromium, or chromium failed), with the reason."""


def chromium_or_error() -> str:
    """The chromium executable, else :class:`PdfError` saying how to install it."""
    exe = find_chromium()
    if exe is None:
        raise PdfError(
            "printing a PDF needs Debian's chromium, which is not installed "
            "(sudo apt-get install chromium, or bash tools/install-browser.sh)"
        )
    return exe


def print_pdf(html_path: str | Path, pdf_path: str | Path, timeout_s: float = 180.0) -> Path:
    """Print ``html_path`` to ``pdf_path`` (A4, backgrounds, no header/footer) and return it;
    written to a temp file and renamed."""
    exe = chromium_or_error()
    html_path, pdf_path = Path(html_path).resolve(), Path(pdf_path)
    if not html_path.is_file():
        raise PdfError(f"{html_path}: no such report")
    pdf_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = pdf_path.with_name(f".{pdf_path.name}.tmp")
    with tempfile.TemporaryDirectory(prefix="mimucal-pdf-") as profile:
        cmd = [
            exe,
            *FLAGS,
            f"--user-data-dir={profile}",
            "--no-pdf-header-footer",
            "--run-all-compositor-stages-before-draw",
            f"--virtual-time-budget={SCRIPT_BUDGET_MS}",
            f"--print-to-pdf={tmp}",
            html_path.as_uri(),
        ]
        try:
            out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
        except subprocess.TimeoutExpired:
            tmp.unlink(missing_ok=True)
            raise PdfError(f"chromium did not print {html_path.name} within {timeout_s:.0f} s") from None
    if out.returncode != 0 or not tmp.is_file() or tmp.stat().st_size == 0:
        tmp.unlink(missing_ok=True)
        last = (out.stderr.strip().splitlines() or ["no message"])[-1]
        raise PdfError(f"chromium could not print {html_path.name} (exit {out.returncode}: {last})")
    tmp.replace(pdf_path)
    return pdf_path


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: python -m reports.pdf REPORT.html OUT.pdf")
    try:
        print(print_pdf(sys.argv[1], sys.argv[2]))
    except PdfError as exc:
        sys.exit(f"reports.pdf: error: {exc}")
