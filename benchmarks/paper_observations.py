"""The paper's three observations tested on the rotation-sense study's exports (issue 37; runs no DEM).

Reads ``benchmarks/data/rotation_sense/<config>/<run>/statistics.json`` (written by
``scripts/rotation_sense_study.py``) and tests, per configuration, (a) stage-1 kickback below every
other stage's, (b) pass-through rising with shaft speed, (c) stage-1 refeed falling with rock size,
as defined in :mod:`msmill.dem.mill.observations` (agree: the paper's sign with ``|z| > 2``).
Prints the effects and z-values (lines starting ``#``), then one line per configuration::

    config=<name> top_least_kickback=<agree|disagree> pass_rises_with_speed=<agree|disagree> refeed_falls_with_size=<agree|disagree>

and last ``default=<name> agreeing=<k>/3`` (ties broken by the share of steady runs, then by the
statements with the paper's sign, then by the sum of the signed z clipped to +-5)::

    python benchmarks/paper_observations.py [--root benchmarks/data/rotation_sense] [--brief] [--table]
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

from msmill.dem.mill.observations import (
    evaluate,
    leave_one_seed_out,
    read_study,
    report_lines,
    scatter_over_error,
    stream_table_lines,
)

ROOT = Path(__file__).parent / "data" / "rotation_sense"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, default=ROOT)
    ap.add_argument("--brief", action="store_true", help="only the key=value lines")
    ap.add_argument("--table", action="store_true", help="first a Markdown table of the group means (streams per stage)")
    ap.add_argument("--include-not-steady", action="store_true", help="also use runs that did not reach steady state")
    args = ap.parse_args(argv)
    runs = read_study(args.root)
    if args.table:
        print("\n".join(stream_table_lines(runs)))
    if not args.brief:
        per = Counter((r.config, r.size_mm, r.speed_rpm) for r in runs)
        for (c, size, rpm), n in sorted(per.items()):
            print(f"# runs {c} {size:g} mm {rpm:g} rpm: {n} seeds")
    lines = report_lines(evaluate(runs, include_not_steady=args.include_not_steady), details=not args.brief)
    if not args.brief:
        used = runs if args.include_not_steady else [r for r in runs if r.outcome == "steady"]
        for stream, (ratio, n) in scatter_over_error(used).items():
            print(f"# between-seed sd / sampling error, {stream}: median {ratio:.2f} over {n} groups")
        for seed, (pick, k) in leave_one_seed_out(runs, args.include_not_steady).items():
            print(f"# without seed {seed}: default={pick} agreeing={k}/3")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
