"""gearbench report RUN_DIR: the per-unit report (report.html, optionally PDF) of a finished run."""
from __future__ import annotations

from pathlib import Path

NAME = "report"
HELP = "Write the per-unit report (self-contained report.html, optionally PDF) of a run folder."


def add_arguments(p) -> None:
    p.add_argument("run_dir", metavar="RUN_DIR", help="output folder of 'gearbench run'")
    p.add_argument("--out", help="report file (default RUN_DIR/report.html)")
    p.add_argument("--pdf", action="store_true", help="also print it to PDF (needs Chromium)")


def run(args) -> int:
    from ..reports.unit_report import write_pdf, write_report

    path = write_report(args.run_dir, args.out)
    print(f"gearbench report: wrote {path}")
    if args.pdf:
        pdf = write_pdf(path, Path(path).with_suffix(".pdf"))
        print(f"gearbench report: wrote {pdf}")
    return 0
