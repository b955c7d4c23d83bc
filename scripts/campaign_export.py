"""Write the store's campaign export into git (``src/msmill/data/campaigns/default/``).

One ``run-<hash>.json`` per done run (statistics and provenance; raw tables by
reference only) and ``campaigns.json`` (campaign definitions and their pending
points). Commit the folder after every batch; on another machine::

    msmill db ingest src/msmill/data/campaigns/default    # or the installed package's copy
    python scripts/campaign_loop.py --rounds 0             # re-creates the campaigns, plans nothing
    msmill campaign resume NAME

    python scripts/campaign_export.py [--db URL] [--out DIR]
"""

from __future__ import annotations

import argparse
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXPORT = ROOT / "src/msmill/data/campaigns/default"


def main(argv: list[str] | None = None) -> None:
    """Command line entry point."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--db", default=None, help="store URL (default $MSMILL_DB or the user store)")
    ap.add_argument("--out", type=Path, default=EXPORT, help="export folder")
    a = ap.parse_args(argv)
    from msmill.pipeline.export import export_campaign
    from msmill.pipeline.store import Store

    with Store(a.db) as st:
        runs, cpath = export_campaign(st, a.out)
    print(f"exported {len(runs)} runs and {cpath.name} to {a.out}")
    print(f"commit: git -C {ROOT} add {a.out} && git -C {ROOT} commit -m 'campaign export: {len(runs)} runs'")


if __name__ == "__main__":
    main()
