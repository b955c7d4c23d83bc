"""Campaigns: run the planned DEM runs of the store on Dask, surviving crashes.

A campaign (``msmill campaign create``) is a named set of design points in
the store with one DEM setting: machine, slice or full mode, and
:class:`msmill.dem.mill.run.RunSettings` fields (stored as JSON and passed
through unchanged, so new run-protocol settings need no change here).
A campaign created through :func:`run_settings_dict` (``msmill campaign
create``, ``scripts/campaign_loop.py``) starts from
:data:`CAMPAIGN_RUN_DEFAULTS`: every run starts from the default stage
table's expected hold-up (``start = "table"``) and measures with the adaptive
window (``adaptive = true``) from the steady-state onset (``window_from =
"onset"``); ``--set start=empty``, ``--set adaptive=false`` or ``--set
window_from=detection`` switches each off. The settings are stored with the campaign, so they are
explicit in the store and in every run's provenance.

:func:`run_campaign` is the driver. It keeps every worker thread of a Dask
cluster busy (its own ``distributed.LocalCluster``, one single-threaded
worker process per core with numba limited to one thread, or an existing
scheduler). Workers only compute (:func:`execute_run`) and return the
statistics; the driver claims runs, writes results, heartbeats the runs it
holds, and retries failed runs up to the campaign's attempt limit.

Fault behaviour (``docs/campaign.md``):

* a worker process dies: Dask reschedules its task on another worker (the
  nanny restarts the dead one); after ``distributed.scheduler.allowed-failures``
  deaths of the same task it fails with ``KilledWorker`` and counts as a
  failed attempt;
* the driver dies: its runs stay ``running`` with a heartbeat that goes stale;
  the next driver (``campaign resume``, or any ``campaign run``) re-plans
  runs whose heartbeat is older than ``stale_s``; results of the dead driver
  are lost with it and the runs are computed again, never recorded twice
  (claim tokens, :mod:`msmill.pipeline.store.queue`);
* a done run is never claimed again.

``plan_hook``: :data:`PLANNERS` maps a planner name to a callable
``planner(store, campaign_name, n) -> list[DesignPoint]`` used by
``msmill campaign plan`` (the active-learning planner registers itself here).
"""

from __future__ import annotations

import dataclasses
import os
import socket
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from msmill.errors import MsmillInputError
from msmill.pipeline.store import Store
from msmill.pipeline.store.hashing import file_sha256, outcome_of, read_statistics
from msmill.pipeline.store.queue import Claim, new_token
from msmill.stageparams import DesignPoint, RunStatistics, design_inputs

if TYPE_CHECKING:
    from msmill.surrogate.space import DesignSpace

__all__ = ["CAMPAIGN_RUN_DEFAULTS", "DEFAULT_STALE_S", "PLANNERS", "CampaignReport", "checkpoint_base", "design_grid",
           "execute_run", "nearest_run_start", "run_campaign", "run_checkpoint_dir", "run_settings_dict"]

#: heartbeat age after which a running run is taken to be lost (s)
DEFAULT_STALE_S = 120.0
#: planner name -> planner(store, campaign, n) -> list of DesignPoint (filled by the surrogate's active learning)
PLANNERS: dict[str, Callable[[Store, str, int], list[DesignPoint]]] = {}
#: ``RunSettings`` fields a new campaign gets unless set (issue 12): warm start from the stage
#: table's hold-up, adaptive measurement window from the steady-state onset
CAMPAIGN_RUN_DEFAULTS: dict[str, Any] = {"start": "table", "adaptive": True, "window_from": "onset"}


def active_planner(store: Store, name: str, n: int, seed: int = 0, cost_power: float = 1.0,
                   max_run_hours: float | None = None) -> list[DesignPoint]:
    """Next ``n`` design points of a campaign by the surrogate's cost-aware active learning.

    Fits :class:`msmill.surrogate.stage_model.StageSurrogate` to the store's
    steady runs of the campaign's machine (a space-filling Sobol design while
    there are too few), within the campaign's size range (option
    ``size_range_mm``, default the paper's 2-30 mm), avoids the campaign's planned, running and failed points
    (kriging believer) and weights the acquisition by the DEM cost learnt from
    the runs' timings (:func:`msmill.surrogate.active.plan_batch`). No point whose expected wall time
    exceeds ``max_run_hours`` (default: the campaign's option ``max_run_hours``, else no cap) is planned.
    """

    from msmill.machine import OperatingPoint
    from msmill.surrogate.active import CostModel, plan_batch
    from msmill.surrogate.space import DesignSpace
    from msmill.surrogate.stage_model import StageSurrogate

    info = store.campaign(name)
    size_range = info.options.get("size_range_mm")
    space = DesignSpace(size_mm=tuple(size_range)) if size_range else DesignSpace()
    machine = info.machine
    pairs = store.training_runs(machine_hash=info.machine_hash)
    runs = [st for _, st in pairs]
    # failed points count as pending too: re-proposing one would add nothing (the store keeps a point once)
    # and stall the campaign on a point its workers cannot finish
    pending = [r.design for r in store.runs(campaign=name) if r.status in ("planned", "running", "failed")]
    pend = design_inputs(pending)
    model = StageSurrogate().fit(runs).gp_ if len(runs) >= 2 else None
    cap_h = max_run_hours if max_run_hours is not None else info.options.get("max_run_hours")
    plan = plan_batch(model, n, space, n_existing=len(runs), pending=pend if len(pend) else None,
                      cost=CostModel.from_runs(runs, space), cost_power=cost_power, seed=seed,
                      max_cost_s=None if cap_h is None else 3600.0 * float(cap_h))
    out = []
    for size, feed, speed, gate in plan.points:
        op = OperatingPoint(feed_tph=float(feed), speed_rpm=float(speed), gate_deg=float(gate))
        out.append(DesignPoint(size_mm=float(size), feed_tph=float(feed), speed_rpm=float(speed),
                               gate_deg=float(gate), stage_speeds_rpm=op.stage_speeds(machine.n_stages)))
    return out


PLANNERS["active"] = active_planner


def run_settings_dict(values: dict[str, Any], defaults: dict[str, Any] | None = None) -> dict[str, Any]:
    """Validate ``RunSettings`` fields (names and types) and return them as a plain dict.

    Parameters
    ----------
    values : dict
        Field name -> value (strings are converted to the field's type).
    defaults : dict, optional
        Fields added where ``values`` does not set them; None (default):
        :data:`CAMPAIGN_RUN_DEFAULTS`; ``{}`` validates ``values`` alone.
    """
    from msmill.dem.backend import check_backend
    from msmill.dem.mill.checks import check_start, check_window_from
    from msmill.dem.mill.run import RunSettings

    values = {**(CAMPAIGN_RUN_DEFAULTS if defaults is None else defaults), **values}
    names = {f.name for f in dataclasses.fields(RunSettings)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise MsmillInputError("run setting", ", ".join(unknown), ", ".join(sorted(names)))
    field_defaults = dataclasses.asdict(RunSettings())
    out = {}
    for k, v in values.items():
        d = field_defaults[k]
        if isinstance(d, bool):  # bool("false") is True: parse the words
            out[k] = _parse_bool(k, v)
            continue
        try:
            out[k] = v if v is None or d is None else type(d)(v)
        except (TypeError, ValueError):
            raise MsmillInputError(k, v, f"a {type(d).__name__}") from None
    check_start(out.get("start", "empty"))
    check_window_from(out.get("window_from", "detection"))
    if "backend" in out:
        check_backend(out["backend"], here=False)  # the workers' machines check that they can run it
    return out


def _parse_bool(name: str, value: Any) -> bool:
    if isinstance(value, bool):
        return value
    word = str(value).strip().lower()
    if word in ("true", "1", "yes", "on"):
        return True
    if word in ("false", "0", "no", "off"):
        return False
    raise MsmillInputError(name, value, "true or false")


# --------------------------------------------------------------------------- worker side
def _worker_name() -> str:
    try:
        from distributed import get_worker

        return str(get_worker().address)
    except (ImportError, ValueError):
        return f"{socket.gethostname()}:{os.getpid()}"


def execute_run(task: dict[str, Any]) -> dict[str, Any]:
    """Run the DEM of one campaign run (on a worker); returns the statistics and run facts.

    ``task`` holds ``machine_toml``, ``design`` (DesignPoint fields), ``mode``,
    ``run_settings`` (RunSettings fields), ``options`` (``ore``; ``raw_dir``:
    save the raw run folder there), ``run_id``/``attempt`` and ``checkpoint_dir``
    (None: no checkpoints) and ``threads`` (numba threads of the run's step kernels, default 1: one
    core per worker; more gives a long fine-rock run the cores that idle workers would leave, and the
    kernels' results do not depend on it). A checkpoint there from an earlier attempt of the
    run (a killed worker, a stopped machine) is continued if it matches the
    run's inputs and the code, and otherwise removed, with a ``note`` saying
    why; the driver removes the checkpoint once the result is recorded.
    """
    try:
        import numba

        numba.set_num_threads(int(task.get("threads", 1)))
    except (ImportError, ValueError):
        pass
    from msmill._version import __version__
    from msmill.dem.checkpoint import has_checkpoint, remove_checkpoint
    from msmill.dem.mill.run import RunSettings, check_checkpoint, run_inputs, run_mill, save_run
    from msmill.machine import Machine, OperatingPoint

    machine = Machine.from_toml(task["machine_toml"])
    d = DesignPoint(**task["design"])
    op = OperatingPoint(feed_tph=d.feed_tph, stage_speeds_rpm=d.stage_speeds_rpm, gate_deg=d.gate_deg)
    settings = RunSettings(**task["run_settings"])
    opts = task.get("options", {})
    ckpt = task.get("checkpoint_dir")
    note = None
    if ckpt and has_checkpoint(ckpt) and task.get("start_residence_from"):
        # the nearest run may have changed since the attempt that wrote the checkpoint: keep its start
        from msmill.dem.checkpoint import read_header

        given = read_header(ckpt).get("inputs", {}).get("settings", {}).get("start_residence_s")
        if given is not None:
            settings = dataclasses.replace(settings, start_residence_s=list(given))
    if ckpt and has_checkpoint(ckpt):  # an earlier attempt was stopped: continue it if it is this run's
        try:
            check_checkpoint(ckpt, run_inputs(machine, op, d.size_mm, None, task["mode"], None, opts.get("ore"),
                                              settings, None, None))
        except MsmillInputError as exc:
            note = f"started afresh: {exc}"
            remove_checkpoint(ckpt)
    run = run_mill(machine, op, size_mm=d.size_mm, mode=task["mode"], settings=settings, ore=opts.get("ore"),
                   checkpoint_dir=ckpt)
    parts = run.extra.get("parts", [])
    if len(parts) > 1:
        note = (f"resumed from its checkpoint {len(parts) - 1} time(s); parts (sim s, wall s): "
                + ", ".join(f"{p['sim_from_s']:.2f}-{p['sim_to_s']:.2f} {p['wall_s']:.0f}" for p in parts))
    stats = run.stats.run
    raw: list[dict[str, Any]] = []
    if opts.get("raw_dir"):
        folder = save_run(run, Path(opts["raw_dir"]) / f"run{task['run_id']:06d}-a{task['attempt']}")
        raw = [{"kind": p.stem, "path": str(p.resolve()), "sha256": file_sha256(p), "size_bytes": p.stat().st_size}
               for p in sorted(folder.glob("*.parquet"))]
    if task.get("start_residence_from"):
        note = "; ".join(x for x in (note, f"started from the residence of {task['start_residence_from']}") if x)
    return {"statistics": stats.model_dump_json(), "outcome": run.extra.get("outcome") or outcome_of(stats),
            "wall_s": run.wall_s, "cpu_s": run.extra.get("cpu_s"), "note": note,
            "engine": f"msmill.dem {__version__}", "package_version": __version__,
            "git_commit": run.extra.get("git_commit"), "raw_files": raw, "worker": _worker_name()}


# --------------------------------------------------------------------------- driver side
@dataclass
class CampaignReport:
    """What one driver session did."""

    recorded: int = 0  # results written by this driver
    failed_attempts: int = 0
    rejected: int = 0  # results arriving after this driver lost the claim (not written)
    replanned_stale: int = 0
    elapsed_s: float = 0.0
    counts: dict[str, int] = field(default_factory=dict)


def _cluster_client(scheduler: str | None, n_workers: int | None, threads_per_run: int = 1) -> tuple[Any, Any]:
    from distributed import Client, LocalCluster

    if scheduler:
        return Client(scheduler), None
    n = n_workers or max(1, (os.cpu_count() or 1) // threads_per_run)
    env = {"NUMBA_NUM_THREADS": str(threads_per_run), "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
           "OPENBLAS_NUM_THREADS": "1"}  # one run per worker process; numba's pool sized for it
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=":0",
                           env=env, silence_logs=50)  # task errors are recorded in the store
    return Client(cluster), cluster


def checkpoint_base(store: Store, info: Any) -> Path | None:
    """Folder of a campaign's run checkpoints (one sub-folder per run), or None if the campaign has none.

    The campaign's ``checkpoint_dir`` option (``msmill campaign create --checkpoint-dir``; ``"none"``
    switches checkpoints off), else a folder per store and campaign under the per-user data folder
    (``$XDG_DATA_HOME/msmill/checkpoints``). Workers on other machines need the option, on a file
    system they share with the driver.
    """
    import hashlib

    from msmill.pipeline.store.core import data_home

    opt = info.options.get("checkpoint_dir")
    if opt == "none":
        return None
    if opt:
        return Path(opt)
    return data_home() / "checkpoints" / hashlib.sha256(store.url.encode()).hexdigest()[:12] / info.name


def run_checkpoint_dir(base: Path, run_id: int) -> Path:
    """A campaign run's own checkpoint folder under :func:`checkpoint_base`."""
    return base / f"run{run_id:06d}"


def _task(store_info: Any, claim: Claim, ckpt_base: Path | None = None, threads: int = 1,
          start: tuple[list[float], str] | None = None) -> dict[str, Any]:
    settings = dict(store_info.run_settings, seed=claim.seed)
    if start is not None:
        settings["start_residence_s"] = start[0]
    return {"machine_toml": store_info.machine_toml, "design": claim.design.model_dump(), "mode": store_info.mode,
            "run_settings": settings, "options": store_info.options,
            "run_id": claim.run_id, "attempt": claim.attempt, "threads": threads,
            "checkpoint_dir": None if ckpt_base is None else str(run_checkpoint_dir(ckpt_base, claim.run_id)),
            "start_residence_from": None if start is None else start[1]}


def nearest_run_start(runs: Sequence[RunStatistics], design: DesignPoint,
                      space: DesignSpace | None = None) -> tuple[list[float], str] | None:
    """The steady residence per compartment (:meth:`RunStatistics.compartment_residence_s`) of the run
    nearest to ``design`` in the unit design cube (size in ln), and a line naming that run.

    What a campaign with the ``start_from_nearest_run`` option places at the start of each run
    (``RunSettings.start_residence_s``): the stage table's hold-up is off far from its 30 t/h point,
    and the finer the rock the longer a run takes to drain or fill to its steady hold-up
    (``docs/mill-dem.md``, "A start from a finished run's residence"). None without a run that has
    the hold-ups and the rate.
    """
    from msmill.surrogate.space import DesignSpace

    have = [(r, res) for r in runs if (res := r.compartment_residence_s()) is not None
            and r.n_stages == len(design.stage_speeds_rpm)]
    if not have:
        return None
    space = space or DesignSpace()
    u = space.to_unit(np.array([r.design.inputs() for r, _ in have]))
    d = np.linalg.norm(u - space.to_unit(np.array(design.inputs())), axis=1)
    r, res = have[int(np.argmin(d))]
    x = r.design
    return res, (f"the run at {x.size_mm:.3g} mm, {x.feed_tph:.3g} t/h, {x.speed_rpm:.0f} rpm, gate "
                 f"{x.gate_deg:.3g} deg ({float(np.min(d)):.2f} of the unit design cube away)")


class _Driver:
    """State of one driver session (kept small: the store holds the truth)."""

    def __init__(self, store: Store, name: str, client: Any, executor: Callable[[dict[str, Any]], dict[str, Any]],
                 heartbeat_s: float, stale_s: float, max_runs: int | None, threads: int = 1) -> None:
        self.store, self.name, self.client, self.executor = store, name, client, executor
        self.threads = threads
        self.heartbeat_s, self.stale_s, self.max_runs = heartbeat_s, stale_s, max_runs
        self.token = new_token()
        self.me = f"driver {socket.gethostname()}:{os.getpid()}"
        self.info = store.campaign(name)
        self.ckpt_base = checkpoint_base(store, self.info)
        self.inflight: dict[Any, Claim] = {}
        self.workers: dict[int, str] = {}
        self.report = CampaignReport()
        self.last_beat = self.last_stale = time.monotonic()

    def capacity(self) -> int:
        return max(1, sum(self.client.nthreads().values()))

    def fill(self) -> None:
        free = self.capacity() - len(self.inflight)
        if self.max_runs is not None:
            free = min(free, self.max_runs - self.report.recorded - len(self.inflight))
        if free <= 0:
            return
        runs = None
        for c in self.store.claim(self.name, free, self.me, self.token):
            start = None
            if self._start_from_nearest_run():
                if runs is None:
                    runs = [st for _r, st in self.store.training_runs(machine_hash=self.info.machine_hash)]
                start = nearest_run_start(runs, c.design)
            fut = self.client.submit(self.executor, _task(self.info, c, self.ckpt_base, self.threads, start),
                                     pure=False, key=f"msmill-run{c.run_id}-a{c.attempt}-{self.token[:8]}")
            self.inflight[fut] = c

    def _start_from_nearest_run(self) -> bool:
        rs = self.info.run_settings
        return (bool(self.info.options.get("start_from_nearest_run")) and rs.get("start") == "table"
                and rs.get("start_residence_s") is None)

    def collect(self, fut: Any) -> None:
        c = self.inflight.pop(fut)
        if fut.status == "finished":
            r = fut.result()
            try:
                stats = read_statistics(r["statistics"], source=f"run {c.run_id}")
                ok = self.store.complete(c.run_id, c.token, stats, outcome=r["outcome"], wall_s=r["wall_s"],
                                         engine=r["engine"], package_version=r["package_version"],
                                         git_commit=r["git_commit"], raw_files=r["raw_files"],
                                         worker=r["worker"], cpu_s=r.get("cpu_s"), note=r.get("note"))
            except MsmillInputError as exc:  # an invalid result is a failed attempt, not a driver crash
                self.store.fail(c.run_id, c.token, f"invalid result: {exc}")
                self.report.failed_attempts += 1
                return
            self.report.recorded += ok
            self.report.rejected += not ok
            if ok and self.ckpt_base is not None:  # recorded: the run's checkpoint has served
                from msmill.dem.checkpoint import remove_checkpoint

                remove_checkpoint(run_checkpoint_dir(self.ckpt_base, c.run_id))
            return
        exc = fut.exception()
        text = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__)) if exc else fut.status
        self.store.fail(c.run_id, c.token, text)
        self.report.failed_attempts += 1

    def beat(self) -> None:
        now = time.monotonic()
        if now - self.last_beat >= self.heartbeat_s and self.inflight:
            self.store.heartbeat([c.run_id for c in self.inflight.values()], self.token)
            self.note_workers()
            self.last_beat = now
        if now - self.last_stale >= max(self.stale_s / 4, self.heartbeat_s):
            self.report.replanned_stale += self.store.replan_stale(self.name, self.stale_s, self.token)
            self.last_stale = now

    def note_workers(self) -> None:
        """Record which Dask worker computes each run in flight (when it changed)."""
        where = {k: addr for addr, keys in self.client.processing().items() for k in keys}
        for fut, c in self.inflight.items():
            addr = where.get(fut.key)
            if addr is not None and self.workers.get(c.run_id) != addr:
                self.store.heartbeat([c.run_id], self.token, worker=str(addr))
                self.workers[c.run_id] = addr

    def release_all(self) -> None:
        for fut, c in list(self.inflight.items()):
            fut.cancel()
            self.store.release(c.run_id, c.token)
        self.inflight.clear()


def run_campaign(
    store: Store, name: str, *, scheduler: str | None = None, n_workers: int | None = None, client: Any = None,
    executor: Callable[[dict[str, Any]], dict[str, Any]] = execute_run, heartbeat_s: float = 10.0,
    stale_s: float = DEFAULT_STALE_S, max_runs: int | None = None, retry_failed: bool = False,
    progress: Callable[[dict[str, int], CampaignReport], None] | None = None, threads_per_run: int = 1,
) -> CampaignReport:
    """Execute the planned runs of a campaign until none is left (or ``max_runs`` are recorded).

    Parameters
    ----------
    store, name
        The store and the campaign.
    scheduler : str, optional
        Address of a running Dask scheduler; default: a LocalCluster of ``n_workers``
        worker processes (default: the cores over ``threads_per_run``).
    client : distributed.Client, optional
        Use this client (tests, benchmarks) instead of making one.
    executor : callable
        The worker function (default :func:`execute_run`).
    heartbeat_s, stale_s : float
        Heartbeat interval of the runs this driver holds, and the heartbeat age
        after which another driver's running run is re-planned (s).
    max_runs : int, optional
        Stop after recording this many results.
    retry_failed : bool
        First re-plan the campaign's failed runs with a fresh attempt count.
    progress : callable, optional
        Called after every event with the campaign's status counts and the report.
    threads_per_run : int
        Numba threads of each run's step kernels (default 1), for when one long fine-rock run, not
        many short ones, is what a session can finish (the kernels' gain from a second core:
        ``benchmarks/dem_throughput.py --threads 2``).
    """
    if not isinstance(threads_per_run, int) or threads_per_run < 1:
        raise MsmillInputError("threads_per_run", threads_per_run, "an integer >= 1")
    t0 = time.monotonic()
    made = client is None
    own = None
    if made:
        client, own = _cluster_client(scheduler, n_workers, threads_per_run)
    drv = _Driver(store, name, client, executor, heartbeat_s, stale_s, max_runs, threads_per_run)
    if retry_failed:
        store.retry_failed(name)
    drv.report.replanned_stale += store.replan_stale(name, stale_s)
    try:
        _loop(drv, progress)
    finally:
        drv.release_all()
        if made:
            client.close()
        if own is not None:
            own.close()
    drv.report.elapsed_s = time.monotonic() - t0
    drv.report.counts = store.counts(name)
    return drv.report


def _loop(drv: _Driver, progress: Callable[[dict[str, int], CampaignReport], None] | None) -> None:
    from distributed import wait

    while True:
        drv.fill()
        if not drv.inflight:
            return
        try:
            done, _ = wait(list(drv.inflight), timeout=drv.heartbeat_s, return_when="FIRST_COMPLETED")
        except TimeoutError:
            done = set()
        for fut in done:
            drv.collect(fut)
        drv.beat()
        if progress is not None:
            progress(drv.store.counts(drv.name), drv.report)


def design_grid(machine: Any, sizes_mm: list[float], feeds_tph: list[float], speeds_rpm: list[float],
                gates_deg: list[float], bottom_speed_factor: float = 2.0) -> list[DesignPoint]:
    """Design points of the full grid of the given values (stage speeds from the upper speed and the factor)."""
    import itertools

    from msmill.machine import OperatingPoint

    out = []
    for size, feed, speed, gate in itertools.product(sizes_mm, feeds_tph, speeds_rpm, gates_deg):
        op = OperatingPoint(feed_tph=feed, speed_rpm=speed, bottom_speed_factor=bottom_speed_factor, gate_deg=gate)
        out.append(DesignPoint(size_mm=size, feed_tph=feed, speed_rpm=op.upper_speed_rpm, gate_deg=gate,
                               stage_speeds_rpm=op.stage_speeds(machine.n_stages)))
    return out
