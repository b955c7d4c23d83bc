"""Drive the training campaign: ingest export -> fit -> plan -> run -> export, until a budget or target.

Every step reads and writes the store (``--db`` / ``$MSMILL_DB``) and the
export folder in git (``src/msmill/data/campaigns/default``), so the loop can be
killed at any point and restarted on this or another machine:

1. ingest the export (runs already in the store are recognised by their hash)
   and re-create the exported campaigns missing from the store, with their
   pending points (``msmill.pipeline.export.restore_campaigns``);
2. create the campaign if it still does not exist (``--machine``, ``--size-range-mm``,
   ``--set KEY=VALUE`` run settings);
3. per round: run what is planned (``run_campaign``: stale runs of a dead
   driver are re-planned first), export, then stop if the budget (steady slice
   runs, DEM wall hours) is spent or the leave-one-out mean velocity KL
   (closed form, all steady slice runs of the machine) is at the target, else
   plan ``--batch`` points with the cost-aware active learner
   (``msmill campaign plan``) and go on;
4. print the git command that commits the export (or run it with ``--git-commit``).

    nice -n 5 python scripts/campaign_loop.py --campaign default --size-range-mm 6 30 \\
        --set max_time_s=6 --set measure_s=0.5 --batch 4 --rounds 10 --max-runs 100 --target-kl 0.012

``--rounds 0`` only ingests, restores and exports (e.g. on a new machine
before ``msmill campaign resume``); ``--no-run`` plans without running.
Last line: ``runs=<n> dem_hours=<h> loo_kl_velocity_mean=<x> planned=<p> stop=<reason>``.
"""

from __future__ import annotations

import argparse
import subprocess
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXPORT = ROOT / "src/msmill/data/campaigns/default"


def _settings(items: list[str]) -> dict[str, object]:
    out: dict[str, object] = {}
    for it in items:
        key, _, val = it.partition("=")
        try:
            out[key.strip()] = tomllib.loads(f"v = {val.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            out[key.strip()] = val.strip()
    return out


def prepare(st, a) -> None:
    """Ingest the export, restore its campaigns, create the campaign if missing."""
    from msmill.machine import Machine
    from msmill.pipeline.campaign import run_settings_dict
    from msmill.pipeline.export import restore_campaigns
    from msmill.pipeline.store.transfer import ingest_paths

    if a.export.is_dir():
        res = ingest_paths(st, [a.export], allow_not_steady=True)
        print(f"ingest {a.export}: " + " ".join(f"{k}={sum(r.status == k for r in res)}"
                                                 for k in ("added", "exists", "skipped")))
        for line in restore_campaigns(st, a.export, raw_dir=a.raw_dir):
            print(line)
    if a.campaign not in {c.name for c in st.campaigns()}:
        opts = ({"size_range_mm": list(a.size_range_mm)} | ({"raw_dir": a.raw_dir} if a.raw_dir else {})
                | ({"start_from_nearest_run": True} if a.start_from_nearest_run else {}))
        machine = Machine.default() if a.machine == "default" else Machine.from_toml(Path(a.machine))
        st.create_campaign(a.campaign, machine, run_settings=run_settings_dict(_settings(a.set)),
                           max_attempts=a.max_attempts, options=opts)
        print(f"campaign {a.campaign}: created, sizes {a.size_range_mm[0]:g}-{a.size_range_mm[1]:g} mm")


def progress_state(st, campaign: str) -> dict[str, float]:
    """Steady slice runs of the campaign's machine, their DEM wall hours and the closed-form LOO velocity KL."""
    from msmill.surrogate.accuracy import FINE_SIZE_MM, loo_scores
    from msmill.surrogate.stage_model import StageSurrogate

    info = st.campaign(campaign)
    pairs = [(r, s) for r, s in st.training_runs(machine_hash=info.machine_hash) if r.mode == "slice"]
    hours = sum(r.wall_s or 0.0 for r, _ in pairs) / 3600.0
    kl = kl_fine = float("nan")
    if len(pairs) >= 3:
        rep = loo_scores(StageSurrogate(n_restarts=0).fit([s for _, s in pairs]))
        kl, kl_fine = (rep.summary(below_size_mm=b)["mean_kl_velocity"] for b in (None, FINE_SIZE_MM))
    return {"runs": len(pairs), "dem_hours": hours, "kl": kl, "kl_fine": kl_fine}


def stop_reason(state: dict[str, float], a) -> str | None:
    """Why the campaign stops now, or None."""
    if state["runs"] >= a.max_runs:
        return f"max_runs {a.max_runs}"
    if a.budget_hours is not None and state["dem_hours"] >= a.budget_hours:
        return f"budget {a.budget_hours:g} DEM hours"
    if state["kl"] <= a.target_kl:
        return f"target LOO KL {a.target_kl:g}"
    return None


def export(st, a) -> None:
    """Export the store and print (or run) the git commit of the export folder."""
    from msmill.pipeline.export import export_campaign

    runs, _ = export_campaign(st, a.export)
    cmd = ["git", "-C", str(ROOT), "add", str(a.export)]
    msg = f"campaign {a.campaign}: export {len(runs)} runs"
    if a.git_commit:
        subprocess.run(cmd, check=True)
        subprocess.run(["git", "-C", str(ROOT), "commit", "-m", msg, "--", str(a.export)], check=False)
    else:
        print(f"exported {len(runs)} runs; commit: {' '.join(cmd)} && git -C {ROOT} commit -m '{msg}'")


def one_round(st, a) -> str | None:
    """Run the planned runs, export, check the stop criteria, plan the next batch; the stop reason or None."""
    from msmill.pipeline.campaign import PLANNERS, run_campaign
    from msmill.surrogate.accuracy import FINE_SIZE_MM

    if not a.no_run and (st.counts(a.campaign)["planned"] or st.counts(a.campaign)["running"]):
        rep = run_campaign(st, a.campaign, scheduler=a.scheduler, n_workers=a.workers, stale_s=a.stale_s,
                           threads_per_run=a.threads_per_run)
        print(f"ran: recorded {rep.recorded}, failed attempts {rep.failed_attempts}, {rep.elapsed_s:.0f} s")
        export(st, a)
    state = progress_state(st, a.campaign)
    print(f"state: {state['runs']} steady slice runs, {state['dem_hours']:.2f} DEM hours, "
          f"LOO KL velocity {state['kl']:.4f} (runs below {FINE_SIZE_MM:g} mm: {state['kl_fine']:.4f})")
    a.state = state
    why = stop_reason(state, a)
    if why:
        return why
    if st.counts(a.campaign)["planned"] == 0:
        added, _ = st.add_points(a.campaign, PLANNERS["active"](st, a.campaign, a.batch,
                                                                max_run_hours=a.max_run_hours))
        print(f"planned {added} runs")
    return "planned, not run (--no-run)" if a.no_run else None


def parse(argv: list[str] | None) -> argparse.Namespace:
    """Command line."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--db", default=None, help="store URL (default $MSMILL_DB or the user store)")
    ap.add_argument("--campaign", default="default")
    ap.add_argument("--export", type=Path, default=EXPORT,
                    help="export folder in git (one machine per folder: the envelope and surrogate are per machine)")
    ap.add_argument("--machine", default="default", help="machine TOML of a new campaign, or 'default'")
    ap.add_argument("--size-range-mm", type=float, nargs=2, default=(6.0, 30.0))
    ap.add_argument("--max-run-hours", type=float, default=None,
                    help="plan no point whose expected wall time exceeds this (h; default the campaign's option)")
    ap.add_argument("--set", action="append", default=[], help="RunSettings KEY=VALUE (new campaign only)")
    ap.add_argument("--start-from-nearest-run", action="store_true",
                    help="table starts from the nearest finished run's residence (new campaign only)")
    ap.add_argument("--max-attempts", type=int, default=3)
    ap.add_argument("--raw-dir", default=None, help="workers save raw run folders here")
    ap.add_argument("--batch", type=int, default=4, help="points per active-learning batch")
    ap.add_argument("--rounds", type=int, default=1, help="plan/run rounds in this session (0: prepare only)")
    ap.add_argument("--max-runs", type=int, default=100, help="stop at this many steady slice runs")
    ap.add_argument("--budget-hours", type=float, default=None, help="stop at this many DEM wall hours")
    ap.add_argument("--target-kl", type=float, default=0.012, help="stop at this LOO mean velocity KL")
    ap.add_argument("--scheduler", default=None, help="Dask scheduler address (default: a LocalCluster)")
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--threads-per-run", type=int, default=1, help="numba threads of each run (default 1)")
    ap.add_argument("--stale-s", type=float, default=120.0)
    ap.add_argument("--no-run", action="store_true", help="plan but do not run")
    ap.add_argument("--git-commit", action="store_true", help="commit the export folder after each batch")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    """Command line entry point."""
    from msmill.pipeline.store import Store

    a = parse(argv)
    a.state = {"runs": 0, "dem_hours": 0.0, "kl": float("nan")}
    with Store(a.db) as st:
        prepare(st, a)
        why = "rounds done"
        for _ in range(a.rounds):
            r = one_round(st, a)
            if r:
                why = r
                break
        export(st, a)
        s, c = a.state, st.counts(a.campaign)
    print(f"runs={s['runs']} dem_hours={s['dem_hours']:.2f} loo_kl_velocity_mean={s['kl']:.4f} "
          f"planned={c['planned']} stop={why.replace(' ', '_')}")


if __name__ == "__main__":
    main()
