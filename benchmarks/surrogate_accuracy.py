"""Leave-one-out accuracy of the shipped default surrogate, recomputed from its file and the campaign export.

Loads ``msmill/data/surrogates/default.json`` (or ``--surrogate``), checks that
its training runs are the steady slice runs of the campaign export
(``msmill/data/campaigns/default``, or ``--export``), recomputes the
leave-one-out figures of ``docs/surrogate.md`` (refit by default: every GP
refitted without the held-out run, hyperparameters warm-started) and prints
them per stage. The paper's figure: mean KL 0.012 after 177 runs.

    python benchmarks/surrogate_accuracy.py [--surrogate FILE] [--export DIR] [--loo refit|closed]

The line before the last: the closed-form leave-one-out coverage of the 90 % predictive interval per
kind of target (``coverage90_streams=... coverage90_hit=... coverage90_count=... coverage90_velocity=...``,
:func:`msmill.surrogate.accuracy.loo_coverage`). Last line: ``runs=<n> domain_size_mm=<lo>-<hi>
loo_kl_velocity_mean=<x> loo_kl_count_mean=<y> stream_mae=<z> hit_prob_mae=<w> runs_fine=<m>
loo_kl_velocity_mean_fine=<v>``, the last two over the runs of rock finer than 6.4 mm (the size the
first campaign stopped at; ``nan`` when there are none).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> None:
    """Command line entry point."""
    from msmill.model.providers import default_surrogate_path
    from msmill.pipeline.export import default_export_dir, read_export, split_runs
    from msmill.surrogate.accuracy import FINE_SIZE_MM, loo_coverage, loo_scores
    from msmill.surrogate.persist import load

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--surrogate", type=Path, default=None, help="surrogate JSON (default: the shipped one)")
    ap.add_argument("--export", type=Path, default=None, help="campaign export folder (default: the shipped one)")
    ap.add_argument("--loo", choices=("refit", "closed"), default="refit")
    a = ap.parse_args(argv)
    path = a.surrogate or default_surrogate_path()
    if path is None:
        sys.exit("no shipped surrogate: run scripts/build_default_surrogate.py first")
    model = load(path)
    slices, fulls = split_runs(read_export(a.export or default_export_dir()))
    trained = {r.model_dump_json() for r in model.training_.runs}
    exported = {r.statistics.model_dump_json() for r in slices}
    print(f"surrogate {path}: {model.training_.n_runs} training runs; export: {len(slices)} steady slice runs, "
          f"{len(fulls)} full-mill runs; in both: {len(trained & exported)}")
    if trained != exported:
        print("WARNING: the surrogate is not trained on exactly the export's runs "
              "(re-run scripts/build_default_surrogate.py)")
    t0 = time.process_time()
    rep = loo_scores(model, refit=a.loo == "refit")
    print(f"{rep.method}, {time.process_time() - t0:.1f} s CPU")
    print(rep.per_stage.round(4).to_string())
    bias = getattr(model, "slice_to_full_", None)
    if bias is not None:
        print("slice-to-full lambda factor per stage: " + ", ".join(
            f"{d['lambda_factor']:.2f}+-{d['lambda_factor_sd']:.2f}"
            for d in bias.lambda_factors(model.training_.layout)) + f" ({bias.n_pairs} pairs)")
    s = rep.summary()
    fine = rep.summary(below_size_mm=FINE_SIZE_MM)
    sizes = model.training_.X[:, 0]
    print(f"paper: mean KL 0.012 after 177 runs; here {s['mean_kl_velocity']:.4f} after {s['n_runs']} runs")
    cov = loo_coverage(model, 0.9)
    print("closed-form LOO coverage of the 90 % predictive interval (target space, noise included): "
          + " ".join(f"coverage90_{k}={v:.3f}" for k, v in cov.items()))
    print(f"runs={s['n_runs']} domain_size_mm={sizes.min():g}-{sizes.max():g} "
          f"loo_kl_velocity_mean={s['mean_kl_velocity']:.4f} loo_kl_count_mean={s['mean_kl_count']:.4f} "
          f"stream_mae={s['stream_mae']:.4f} hit_prob_mae={s['hit_probability_mae']:.4f} "
          f"runs_fine={fine['n_runs']} loo_kl_velocity_mean_fine={fine['mean_kl_velocity']:.4f}")


if __name__ == "__main__":
    main()
