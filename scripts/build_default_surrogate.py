"""Train the shipped default surrogate from the campaign export in git.

Reads the run documents of ``src/msmill/data/campaigns/default/`` (written by
``scripts/campaign_export.py``), fits the Gaussian-process surrogate
(``msmill.surrogate.stage_model.StageSurrogate``) to the steady periodic-slice
runs, estimates the slice-to-full-mill correction
(``msmill.surrogate.fidelity.SliceToFullBias``) from the steady full-mill runs
paired with a slice run at the same design point, scores it by leave-one-out
and writes ``src/msmill/data/surrogates/default.json`` with provenance
(command, commit, versions, date, the runs used, LOO metrics, domain).

    python scripts/build_default_surrogate.py [--export DIR] [--out FILE] [--loo refit|closed]
    python scripts/build_default_surrogate.py --amend-filling-curves table [--out FILE]

The campaign's runs start from a filled mill, so the file says its filling curves are the packaged
stage table's (``filling_curves``, :attr:`msmill.surrogate.stage_model.StageSurrogate.filling_curves`).
``--amend-filling-curves`` writes that field into an existing file without refitting (every other
byte stays), and records the amendment in its provenance.

``msmill predict`` and ``Mill(ore, "default")`` use the file when it is installed.
"""

from __future__ import annotations

import argparse
import datetime as dt
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
EXPORT = ROOT / "src/msmill/data/campaigns/default"
OUT = ROOT / "src/msmill/data/surrogates/default.json"


def git_state() -> dict[str, object]:
    """Commit of the repository and whether the export folder has uncommitted changes."""
    from msmill.provenance import git_commit, git_uncommitted

    return {"git_commit": git_commit() or "unknown", "export_uncommitted": git_uncommitted([EXPORT])}


def train(export: Path, loo: str = "refit", n_restarts: int = 2, correct: bool = True,
          groups: tuple[str, ...] | None = ("count",), filling_curves: str | None = "table", n_levels: int = 28):
    """Fit, correct and score; returns ``(model, report, provenance)``."""
    from msmill.pipeline.export import read_export, runs_machine, split_runs
    from msmill.surrogate.accuracy import FINE_SIZE_MM, loo_scores
    from msmill.surrogate.fidelity import SliceToFullBias, match_pairs
    from msmill.surrogate.stage_model import StageSurrogate

    runs = read_export(export)
    slices, fulls = split_runs(runs)
    if len(slices) < 2:
        sys.exit(f"{export}: {len(slices)} steady slice runs; at least 2 are needed")
    model = StageSurrogate(n_restarts=n_restarts, filling_curves=filling_curves,
                           n_levels=n_levels).fit([r.statistics for r in slices])
    pairs = match_pairs([r.statistics for r in slices], [r.statistics for r in fulls]) if correct else []
    if pairs:
        model.slice_to_full_ = SliceToFullBias.fit(model.training_.layout, pairs, groups=groups)
        full = SliceToFullBias.fit(model.training_.layout, pairs)
        lay = model.training_.layout
        measured = {g: {"mean_abs_offset": float(np.mean([np.abs(full.offset[lay.slices(s)[g]]).mean()
                                                          for s in range(1, lay.n_stages + 1)])),
                        "mean_sd": float(np.mean([np.sqrt(full.var[lay.slices(s)[g]]).mean()
                                                  for s in range(1, lay.n_stages + 1)]))}
                    for g, _ in lay.groups()}
    else:
        measured = {}
    report = loo_scores(model, refit=loo == "refit")
    dom = model.domain_
    machine = runs_machine([*slices, *fulls])
    prov = {
        "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
        **git_state(),
        "inputs": {"export": str(export.relative_to(ROOT) if export.is_relative_to(ROOT) else export),
                   "n_documents": len(runs), "n_steady_slice": len(slices), "n_steady_full": len(fulls),
                   "n_pairs": len(pairs),
                   "excluded": sorted(r.path.name for r in runs if r.outcome != "steady")},
        "machine": {"name": machine.name, "rotation_sense": machine.rotation_sense,
                    "geometry_hash": machine.geometry_hash()},
        "runs": [{"file": r.path.name, "content_hash": r.content_hash, "size_mm": r.statistics.design.size_mm,
                  "feed_tph": r.statistics.design.feed_tph, "speed_rpm": r.statistics.design.speed_rpm,
                  "gate_deg": r.statistics.design.gate_deg, "wall_s": r.wall_s} for r in slices],
        "loo": {"method": report.method, **report.summary(),
                "fine": {"below_size_mm": FINE_SIZE_MM, **report.summary(below_size_mm=FINE_SIZE_MM)},
                "per_stage": report.per_stage.reset_index().to_dict(orient="list")},
        "domain": {k: [float(v) for v in dom[i]] for i, k in
                   enumerate(("size_mm", "feed_tph", "speed_rpm", "gate_deg"))},
        "slice_to_full": (model.slice_to_full_.lambda_factors(model.training_.layout) if pairs else
                          "no correction (--no-slice-to-full)" if not correct else
                          "no paired full-mill runs: no correction"),
        "slice_to_full_groups_applied": list(groups) if groups else "all",
        "slice_to_full_measured_target_space": measured,
    }
    return model, report, prov


def amend_filling_curves(path: Path, value: str | None) -> None:
    """Set ``filling_curves`` of the surrogate file at ``path``, keeping every other field as it is."""
    import json

    from msmill.provenance import git_commit
    from msmill.surrogate.persist import from_dict, write_document

    doc = json.loads(path.read_text(encoding="utf-8"))
    doc["filling_curves"] = value
    from_dict(doc, source=path.name)  # a value the loader refuses is refused here
    doc["provenance"].setdefault("amendments", []).append({
        "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]), "git_commit": git_commit() or "unknown",
        "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "change": f"filling_curves = {value!r} (was keyed on the file's path in msmill.model.providers)"})
    write_document(doc, path)
    print(f"wrote {path}: filling_curves={value!r}")


def main(argv: list[str] | None = None) -> None:
    """Command line entry point."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--export", type=Path, default=EXPORT, help="campaign export folder")
    ap.add_argument("--out", type=Path, default=OUT, help="surrogate JSON to write")
    ap.add_argument("--loo", choices=("refit", "closed"), default="refit",
                    help="leave-one-out: refit every GP (honest) or closed form (fast)")
    ap.add_argument("--restarts", type=int, default=2, help="optimiser restarts per target")
    ap.add_argument("--levels", type=int, default=28,
                    help="quantile levels per velocity distribution (msmill.surrogate.targets.SIGMA_FACTORS)")
    ap.add_argument("--correct-groups", default="count",
                    help="target groups the slice-to-full correction is applied to, comma-separated, or 'all' "
                         "(default: count, the secondary impacts the slice is known to under-count)")
    ap.add_argument("--no-slice-to-full", action="store_true",
                    help="ship the slice prediction without the slice-to-full-mill correction")
    ap.add_argument("--filling-curves", choices=("own", "table"), default="table",
                    help="where predictions take filling curves from: the runs' own, or the packaged stage "
                         "table's (default: the campaign's runs start from a filled mill)")
    ap.add_argument("--amend-filling-curves", choices=("own", "table"),
                    help="only write this filling_curves field into --out (no refit)")
    a = ap.parse_args(argv)
    from msmill.surrogate.persist import save

    if a.amend_filling_curves:
        amend_filling_curves(a.out, None if a.amend_filling_curves == "own" else a.amend_filling_curves)
        return

    t0 = time.process_time()
    groups = None if a.correct_groups == "all" else tuple(a.correct_groups.split(","))
    model, report, prov = train(a.export.resolve(), a.loo, a.restarts, not a.no_slice_to_full, groups,
                                None if a.filling_curves == "own" else a.filling_curves, a.levels)
    prov["date_utc"] = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
    prov["cpu_s"] = round(time.process_time() - t0, 1)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    save(model, a.out, provenance=prov)
    s, fine = report.summary(), prov["loo"]["fine"]
    print(f"wrote {a.out} ({a.out.stat().st_size / 1e3:.0f} kB): {s['n_runs']} runs, {report.method}")
    print(report.per_stage.round(4).to_string())
    for k, (lo, hi) in prov["domain"].items():
        print(f"domain {k}: {lo:g}-{hi:g}")
    if isinstance(prov["slice_to_full"], list):
        print("slice-to-full lambda factor per stage: " + ", ".join(
            f"{d['lambda_factor']:.2f}+-{d['lambda_factor_sd']:.2f}" for d in prov["slice_to_full"]))
    print(f"runs={s['n_runs']} loo_kl_velocity_mean={s['mean_kl_velocity']:.4f} "
          f"loo_kl_count_mean={s['mean_kl_count']:.4f} stream_mae={s['stream_mae']:.4f} "
          f"hit_prob_mae={s['hit_probability_mae']:.4f} runs_fine={fine['n_runs']} "
          f"loo_kl_velocity_mean_fine={fine['mean_kl_velocity']:.4f} cpu_s={prov['cpu_s']} "
          f"size_mm={np.min(model.training_.X[:, 0]):g}-{np.max(model.training_.X[:, 0]):g}")


if __name__ == "__main__":
    main()
