"""Secondary-impact count fits of every run and stage of a stage-parameter table.

Refits, from the count histograms stored in the table (schema version 2,
``secondary_count_histogram``), the Poisson and every candidate count family
(:class:`msmill.distributions.CountFamilySelection`, BIC), prints one row per
(run, stage) and, as the last line, the means over all stages of all runs::

    poisson_kl_mean=<x> best_kl_mean=<y> best_kl_max=<z> families=<name:count,...>

``best`` is the family the criterion selects (not the lowest KL).

Run: ``python benchmarks/count_fits.py [--table PATH] [--criterion bic|aic]``
(default: the shipped ``src/msmill/data/stage_parameters/default.json``).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

from msmill.distributions import COUNT_CANDIDATES, CountFamilySelection
from msmill.stageparams import StageParameterTable

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ROOT / "src" / "msmill" / "data" / "stage_parameters" / "default.json"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--table", type=Path, default=DEFAULT)
    ap.add_argument("--criterion", default="bic", choices=["bic", "aic"])
    args = ap.parse_args()
    table = StageParameterTable.from_json(args.table)
    names = list(COUNT_CANDIDATES)
    print(f"table {args.table} ({len(table.runs)} runs)")
    print(f"{'size_mm':>7} {'stage':>5} {'n':>6} " + " ".join(f"{n[:12]:>12}" for n in names) + "  chosen")
    pois, best, chosen = [], [], Counter()
    t0 = time.perf_counter()
    for run in table.runs:
        for st in run.stages:
            if not st.secondary_count_histogram:
                sys.exit(f"error: {run.design.size_mm:g} mm stage {st.stage} has no secondary_count_histogram; "
                         "rebuild the table with scripts/build_stage_table.py --restat")
            sel = CountFamilySelection(criterion=args.criterion).fit_histogram(st.secondary_count_histogram)
            pois.append(sel.poisson_kl_)
            best.append(sel.kl_)
            chosen[sel.chosen_] += 1
            kls = " ".join(f"{sel.fits_[n].kl_:12.4f}" for n in names)
            print(f"{run.design.size_mm:7.3g} {st.stage:5d} {sel.n_samples_:6d} {kls}  {sel.chosen_}")
    print(f"fit time {time.perf_counter() - t0:.1f} s for {len(best)} stages")
    fam = ",".join(f"{k}:{v}" for k, v in sorted(chosen.items()))
    print(f"poisson_kl_mean={np.mean(pois):.4f} best_kl_mean={np.mean(best):.4f} best_kl_max={np.max(best):.4f} "
          f"families={fam}")


if __name__ == "__main__":
    main()
