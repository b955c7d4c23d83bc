"""Generate ``examples/feed_example.csv``: a SYNTHETIC feed PSD in the user CSV format.

A Rosin-Rammler curve ``P = 100 (1 - exp(-(x/x63)^n))`` with ``x63 = 15 mm``
and ``n = 1.2`` (chosen, not measured) read on a sqrt(2) sieve series from
0.5 mm to 32 mm, with 100 % at the top sieve. It only shows the format
(columns ``size_mm``, ``passing_pct``) read by ``msmill psd stats`` and
``msmill.psd.PSD.read_csv``.

Usage::

    python scripts/make_example_feed.py [--out examples/feed_example.csv]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from msmill.psd import SizeGrid

X63_MM, N = 15.0, 1.2


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("examples/feed_example.csv"))
    args = parser.parse_args(argv)
    sizes = SizeGrid.geometric(0.5, 32.0).edges_mm
    passing = 100.0 * (1.0 - np.exp(-((sizes / X63_MM) ** N)))
    passing[-1] = 100.0
    lines = [
        "# SYNTHETIC feed PSD (format sample) from scripts/make_example_feed.py: "
        f"Rosin-Rammler x63={X63_MM} mm, n={N}; not measured data.",
        "size_mm,passing_pct",
    ]
    lines += [f"{s:.4g},{p:.3f}" for s, p in zip(sizes, passing, strict=True)]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n", encoding="utf-8")
    print(f"wrote {args.out} ({sizes.size} sieves)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
