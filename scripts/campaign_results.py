"""Write ``docs/campaign-results.md`` and its figures from the campaign export and the shipped surrogate.

The page and its numbers live in the package (``msmill.cli.campaign_report``, ``msmill.pipeline.results``,
``msmill.plots.campaign``); this script is ``msmill campaign report`` with the same options:

    python scripts/campaign_results.py [--export DIR] [--surrogate FILE] [--envelope FILE] [--out docs/campaign-results.md]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> None:
    """Command line entry point."""
    from msmill.cli.campaign_report import write_campaign_report
    from msmill.errors import MsmillInputError

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--export", type=Path, default=None, help="campaign export folder (default: the packaged one)")
    ap.add_argument("--surrogate", type=Path, default=None, help="surrogate JSON (default: the shipped one)")
    ap.add_argument("--envelope", type=Path, default=None, help="envelope JSON (default: the shipped one)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs/campaign-results.md")
    a = ap.parse_args(argv)
    try:
        write_campaign_report(a.export, a.surrogate, a.envelope, a.out)
    except MsmillInputError as exc:
        sys.exit(f"error: {exc}")


if __name__ == "__main__":
    main()
