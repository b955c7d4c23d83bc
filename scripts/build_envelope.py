"""Build the shipped operating envelope (capacity model) from the campaign export.

Reads the run documents of ``src/msmill/data/campaigns/default/`` (and,
optionally, the done runs of a store not yet exported, e.g. a batch being
ingested), takes each run's outcome (steady / choked / not steady) and measured
throughput, fits the capacity model (``msmill.surrogate.capacity.CapacityModel``, default
the censored log-linear model) and writes ``src/msmill/data/envelopes/default.json``:
the points, the method and fitted parameters (refitted and checked on load, no
pickles; with no choked run the method is ``demonstrated``, lower bounds from the
steady runs, docs/mill-dem.md 3.1), and provenance (command, version, commit, date, inputs, the runs used,
counts per outcome).

    python scripts/build_envelope.py [--export DIR] [--store URL] [--method censored|classifier|demonstrated] [--out FILE]

``msmill predict``, ``Mill.run`` and ``msmill sweep`` / ``optimize`` use the
file when it is installed. Re-run it after the export is rebuilt
(``scripts/rebuild_default_campaign.sh`` does).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXPORT = ROOT / "src/msmill/data/campaigns/default"
OUT = ROOT / "src/msmill/data/envelopes/default.json"
#: points at which the script prints the capacity (size mm, speed rpm, gate deg)
SHOW = ((14.0, 1500.0, 5.0), (14.0, 1500.0, 40.0), (20.0, 1500.0, 10.0), (20.0, 1900.0, 10.0),
        (28.0, 1300.0, 40.0), (28.0, 1800.0, 10.0))


def git_state(paths: list[Path]) -> dict[str, object]:
    """Commit of the repository and whether the inputs have uncommitted changes."""
    from msmill.provenance import git_commit, git_uncommitted

    return {"git_commit": git_commit() or "unknown", "inputs_uncommitted": git_uncommitted(paths)}


def _rel(p: Path) -> str:
    q = p.resolve()
    return str(q.relative_to(ROOT)) if q.is_relative_to(ROOT) else str(p)


def export_rows(export: Path) -> list[dict]:
    """One row per run document of the export: source, hash, machine, mode and the envelope point."""
    from msmill.pipeline.export import read_export
    from msmill.surrogate.capacity import EnvelopePoint

    rows = []
    for r in read_export(export):
        machine = json.loads(r.path.read_text(encoding="utf-8")).get("machine_hash", "")
        rows.append({"source": f"export:{r.path.name}", "content_hash": r.content_hash, "machine_hash": machine,
                     "mode": r.mode, "point": EnvelopePoint.from_statistics(r.statistics.model_copy(
                         update={"outcome": r.outcome}))})
    return rows


def store_rows(url: str, known: set[str]) -> list[dict]:
    """Done runs of a store whose content hash is not among ``known`` (the export's)."""
    from msmill.pipeline.store import Store
    from msmill.surrogate.capacity import EnvelopePoint

    rows = []
    for rec, st in Store(url).training_runs(steady_only=False):
        if rec.content_hash in known:
            continue
        rows.append({"source": f"store:{rec.id}", "content_hash": rec.content_hash, "machine_hash": rec.machine_hash,
                     "mode": rec.mode, "point": EnvelopePoint.from_statistics(st.model_copy(
                         update={"outcome": rec.outcome or st.outcome}))})
    return rows


def build(export: Path, store: str | None, method: str) -> tuple[object, object, dict]:
    """Fit the model; returns ``(model, envelope, provenance)``."""
    from dataclasses import asdict

    from msmill._version import __version__
    from msmill.surrogate.capacity import CapacityModel

    rows = export_rows(export)
    if store:
        rows += store_rows(store, {r["content_hash"] for r in rows})
    machines = sorted({r["machine_hash"] for r in rows})
    if len(machines) != 1:
        sys.exit(f"the runs come from {len(machines)} machines ({', '.join(m[:12] for m in machines)}): "
                 "an envelope is for one machine")
    points = [r["point"] for r in rows]
    if method is None:  # what the data support: a capacity where some run choked, lower bounds where none did
        method = "censored" if any(p.outcome == "choked" for p in points) else "demonstrated"
    if method != "demonstrated" and not any(p.outcome == "choked" for p in points):
        sys.exit(f"{len(points)} runs, none choked: the data give no upper bound on the capacity, so the {method} "
                 "model cannot be fitted (nothing written; --method demonstrated gives the lower bounds)")
    model = CapacityModel.fit(points, method=method)
    counts = {k: sum(p.outcome == k for p in points) for k in ("steady", "choked", "not_steady")}
    prov = {
        "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
        "msmill_version": __version__,
        **git_state([export]),
        "inputs": {"export": _rel(export), "store": store.split("@")[-1] if store else None,
                   "n_runs": len(rows), "machine_hash": machines[0]},
        "counts": counts,
        "method": method,
        "not_used": sorted(r["source"] for r in rows if r["point"].outcome == "not_steady"),
        "runs": [{"source": r["source"], "content_hash": r["content_hash"], "mode": r["mode"], **asdict(r["point"])}
                 for r in rows],
    }
    return model, model.to_envelope(points, prov), prov


def main(argv: list[str] | None = None) -> None:
    """Command line entry point."""
    from msmill.surrogate.capacity import METHODS, load_capacity

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--export", type=Path, default=EXPORT, help="campaign export folder")
    ap.add_argument("--store", default=None, help="also use the done runs of this store (URL) not in the export")
    ap.add_argument("--method", choices=METHODS, default=None,
                    help="capacity model (default: censored when some run choked, else demonstrated: lower bounds)")
    ap.add_argument("--out", type=Path, default=OUT, help="envelope JSON to write")
    a = ap.parse_args(argv)
    t0 = time.process_time()
    model, env, prov = build(a.export.resolve(), a.store, a.method)
    a.method = model.method
    prov["date_utc"] = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
    prov["cpu_s"] = round(time.process_time() - t0, 2)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    env.to_json(a.out)
    again = load_capacity(a.out, refit=True)  # the file rebuilds the same model (warns if not)
    c = prov["counts"]
    print(f"wrote {a.out}: {c['steady']} steady, {c['choked']} choked, {c['not_steady']} not steady (not used); "
          f"method {a.method}")
    if a.method == "censored":
        print("coefficients (log t/h): " + ", ".join(f"{k} {v:.3f}" for k, v in model.params["coefficients"].items())
              + f"; sigma {model.params['sigma']:.3f}")
    if again.lower_bound:
        from msmill.surrogate.capacity import demonstrated_rule

        print(f"lower bounds ({demonstrated_rule()}):")
    for s, v, g in SHOW:
        cap = again.capacity_tph(s, v, g)
        if again.lower_bound:
            print(f"{s:g} mm {v:g} rpm gate {g:g} deg: capacity at least {cap:.0f} t/h")
            continue
        p = again.probability_steady(s, [0.8 * cap, 1.25 * cap], v, g) if cap < float("inf") else [float("nan")] * 2
        print(f"{s:g} mm {v:g} rpm gate {g:g} deg: capacity {cap:.1f} t/h; P(steady) at 0.8x {p[0]:.2f}, "
              f"1.25x {p[1]:.2f}")
    print(f"steady={c['steady']} choked={c['choked']} not_steady={c['not_steady']} method={a.method} "
          f"cpu_s={prov['cpu_s']} capacity_20mm_1500rpm_10deg_tph={again.capacity_tph(20.0, 1500.0, 10.0):.1f}")


if __name__ == "__main__":
    main()
