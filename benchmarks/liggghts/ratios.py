"""Per-round ratios msmill / LIGGGHTS from the output of ``benchmarks/liggghts/alternate.sh``.

Run: ``python benchmarks/liggghts/ratios.py FILE [FILE ...]``. Per solid fraction: the ratio of each
round (the two programs run back to back), their median and the range of each program's
particle-steps per second. Last line: ``rounds=<n> ratio_median_phi005=<x> ratio_median_phi030=<y>``.
"""

from __future__ import annotations

import re
import statistics
import sys

LINE = re.compile(r"round (\d+) (msmill|liggghts) (\S+) load (\S+) (.*)")
FIGURE = re.compile(r"phi=(0\.\d+) particle_steps_per_s=([\d.e+]+)")


def main() -> None:
    rounds: dict[tuple[str, int], dict[str, dict[str, float]]] = {}
    for path in sys.argv[1:]:
        for line in open(path):
            m = LINE.match(line)
            if m:
                figs = {phi: float(x) for phi, x in FIGURE.findall(m[5])}
                rounds.setdefault((path, int(m[1])), {})[m[2]] = figs
    both = [r for r in rounds.values() if "msmill" in r and "liggghts" in r]
    medians = {}
    for phi in ("0.05", "0.30"):
        ratios = [r["msmill"][phi] / r["liggghts"][phi] for r in both]
        ms = [r["msmill"][phi] for r in both]
        ls = [r["liggghts"][phi] for r in both]
        medians[phi] = statistics.median(ratios)
        print(f"phi={phi}: ratios {', '.join(f'{x:.2f}' for x in ratios)}, median {medians[phi]:.2f}; "
              f"msmill {min(ms):.3g}-{max(ms):.3g} (median {statistics.median(ms):.3g}), "
              f"LIGGGHTS {min(ls):.3g}-{max(ls):.3g} (median {statistics.median(ls):.3g}) particle-steps/s")
    print(f"rounds={len(both)} ratio_median_phi005={medians['0.05']:.2f} ratio_median_phi030={medians['0.30']:.2f}")


if __name__ == "__main__":
    main()
