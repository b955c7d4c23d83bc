"""The DEM ``Simulation``: a Python front end that validates, packs and drives the kernels.

See docs/interfaces.md ("DEM engine API") for the contract and docs/dem.md for
the physics, the numerics and the checks.
"""

from __future__ import annotations

import math
import time as _time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from msmill.dem import kernels as K
from msmill.dem.backend import check_backend, device_engine, stepper
from msmill.dem.contact import hertz_contact_time, pair_table
from msmill.dem.geometry import (
    BOX,
    CYL,
    KIND_NAMES,
    NG,
    PLANE,
    Rotation,
    bound_row,
    orthonormal_axes,
    spans_axis,
    vec3,
)
from msmill.dem.io import write_parquet, write_vtu
from msmill.dem.recorder import EventRecorder
from msmill.dem.threads import threads_usable
from msmill.errors import MsmillError, MsmillInputError

#: Largest time step as a fraction of the Hertz contact time. A rotating plate
#: kicking a resting rock (e = 0.2) returns (1 + e) v to 1 % at 0.2 and fewer
#: than 5 steps per contact; at 0.22-0.25 the rebound is 6-7 % low and at 0.3 it is 60 %
#: too fast (the explicit step misses the strongly damped contact).
MAX_SAFETY = 0.2

#: Largest neighbour-cell grid, in cells per particle (at least 4096 cells): above it the longest
#: axis is coarsened. A mill is mostly empty space, so at 8 (until 2026-12-03) a 6 mm slice ran with
#: cells 2 x 1 x 4 cut-offs and ~38 candidates per rock in a rebuild; 64 keeps its cells at the cut-off
#: (docs/dem.md, Performance). Binning costs ~1 ns more per extra cell and rebuild (6 mm slice: 0.08 ms
#: for 32,000 cells, 0.21 ms for 177,000).
CELLS_PER_PARTICLE = 64

#: Geometry-candidate grid: cells along the longest box axis (was 24 until 2026-12-03; the
#: candidate lists are the same, in the same order, with fewer primitives tested per rock)
GEOM_CELLS_LONG_AXIS = 96


class DemRuntimeWarning(UserWarning):
    """A run-time check of the DEM failed softly (overlap, travel per step, lost particles)."""


class DemRuntimeError(MsmillError, RuntimeError):
    """The DEM state became invalid (non-finite values)."""


# per-particle arrays and their trailing shapes; every one is permuted together
_P_FLOAT3 = ("pos", "vel", "omg", "frc", "trq")
_P_SCALAR = ("rad", "mass", "invm", "invi", "flag_t")
# contact-history slots: one 64-byte record per slot (``h_rec`` particle partners, ``g_rec``
# geometry), so a contact's history is one cache line (was: six arrays, six lines); the
# kernels see each field as a strided view (prefix -> (view name, field))
_SLOT_REC = {"h": np.dtype([("pid", "<i8"), ("st", "<f8", (3,)), ("ev", "<i8"), ("pk", "<f8"),
                            ("ds", "<f8"), ("tch", "u1")], align=True),
             "g": np.dtype([("gid", "<i4"), ("st", "<f8", (3,)), ("ev", "<i8"), ("pk", "<f8"),
                            ("ds", "<f8"), ("tch", "u1")], align=True)}
_SLOTS = {"h": (("h_pid", "pid"), ("h_st", "st"), ("h_ev", "ev"), ("h_pk", "pk"), ("h_ds", "ds"),
                ("h_tch", "tch")),
          "g": (("g_gid", "gid"), ("g_st", "st"), ("g_ev", "ev"), ("g_pk", "pk"), ("g_ds", "ds"),
                ("g_tch", "tch"))}
_SLOT_VIEWS = {name for fields in _SLOTS.values() for name, _f in fields}


def _slot_views(p: dict[str, np.ndarray]) -> None:
    """(Re)bind the per-field views of the slot records after they were reallocated."""
    for pre, fields in _SLOTS.items():
        rec = p[f"{pre}_rec"]
        for name, field in fields:
            p[name] = rec[field]


def _pos_number(name: str, value: Any, *, allow_zero: bool = False, allow_inf: bool = False
                ) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = float("nan")
    ok = (v >= 0 if allow_zero else v > 0) and (math.isfinite(v) or (allow_inf and v > 0))
    if not ok:
        what = ">= 0" if allow_zero else "> 0"
        raise MsmillInputError(name, value, f"a finite number {what}")
    return v


class _Schedule:
    """When one :meth:`Simulation.run` samples the time series and takes snapshots (absolute times, s)."""

    def __init__(self, next_ts: float, ts_every: float, next_snap: float, snap_every: float | None,
                 snap_times: list[float]) -> None:
        self.next_ts, self.ts_every = next_ts, ts_every
        self.next_snap, self.snap_every = next_snap, snap_every
        self.snap_times = snap_times

    @classmethod
    def start(cls, sim: Simulation, t_start: float, dt: float, duration: float, timeseries_every_s: float | None,
              snapshot_every_s: float | None, snapshot_times_s: Any) -> _Schedule:
        """The schedule of a run of ``duration`` from ``t_start`` (the arguments of :meth:`Simulation.run`)."""
        # default sampling: 200 samples per run, but never more often than every 500 steps
        # (each sample returns from the compiled loop)
        ts_every = timeseries_every_s or max(duration / 200, 500 * dt)
        next_ts = t_start if not sim._ts else t_start + ts_every
        if snapshot_every_s is not None:
            snapshot_every_s = _pos_number("snapshot_every_s", snapshot_every_s)
        # snapshots on the absolute grid k * snapshot_every_s (regular across repeated runs)
        next_snap = (math.ceil((t_start - 0.5 * dt) / snapshot_every_s) * snapshot_every_s
                     if snapshot_every_s else math.inf)
        try:
            snap_times = sorted(float(x) for x in (snapshot_times_s or ()))
        except (TypeError, ValueError):
            raise MsmillInputError("snapshot_times_s", snapshot_times_s,
                                   "a sequence of times (s)") from None
        return cls(next_ts, ts_every, next_snap, snapshot_every_s, [x for x in snap_times if x >= t_start - 0.5 * dt])

    def record_due(self, sim: Simulation, dt: float) -> None:
        """Sample the time series and take the snapshots due at the simulation's time."""
        t = sim._time
        if t >= self.next_ts - 0.5 * dt:
            sim._record_ts()
            self.next_ts += self.ts_every
        if t >= self.next_snap - 0.5 * dt:
            sim._snaps.append((t, sim.snapshot()))
            self.next_snap += self.snap_every
        if self.snap_times and t >= self.snap_times[0] - 0.5 * dt:
            sim._snaps.append((t, sim.snapshot()))
            while self.snap_times and t >= self.snap_times[0] - 0.5 * dt:
                self.snap_times.pop(0)

    def steps_to_next(self, sim: Simulation, dt: float, limit: int) -> int:
        """Steps (>= 1, <= ``limit``) until the next sample, snapshot or source insertion."""
        for tnext in [self.next_ts, self.next_snap] + self.snap_times[:1] + [s["next"] for s in sim._sources]:
            if math.isfinite(tnext):
                limit = min(limit, max(1, math.ceil((tnext - sim._time) / dt - 1e-9)))
        return limit


class Simulation:
    """A DEM simulation of spheres with analytic (optionally rotating) geometry.

    Parameters
    ----------
    domain_min_m, domain_max_m : sequence of 3 float
        Corners of the simulation box (m). Along non-periodic axes particles
        whose centre leaves the box are deleted as ``lost`` (with a warning).
    periodic : sequence of 3 bool
        Periodic axes.
    gravity_m_s2 : sequence of 3 float
        Gravitational acceleration (m/s^2).
    neighbor_skin_m : float, optional
        Verlet skin (m); default half the smallest particle radius at the
        first run.
    sort_every : int
        Sort particles by cell every this many neighbour-list rebuilds.
    n_chunks : int, optional
        Particle chunks of the parallel loops (default 4 x numba threads).
    max_contacts_per_particle, max_geometry_contacts : int
        History slots per particle (particle and geometry partners).
    parallel_min_particles : int
        Consider the threaded kernels from this many particles on (below,
        opening the parallel regions costs more than it saves; with OpenMP on
        two cores the mill slice gained from threads in every run from ~800
        rocks, ``docs/dem.md``). Above it, ``parallel=None`` times both kinds
        and uses the faster.
    event_buffer_rows : int
        Initial event rows per chunk (buffers are flushed and grown as needed).
    parallel : bool, optional
        Force the threaded (True) or serial (False) step kernels; default:
        time both and use the faster (results are identical either way).
    backend : str
        Step kernels (:mod:`msmill.dem.backend`): ``"cpu"`` (numba, default),
        ``"warp-cpu"`` or ``"cuda"`` (NVIDIA Warp on its CPU device or a GPU;
        state, step and rebuild on that device). One that is unknown or unavailable here
        raises a one-line :class:`MsmillInputError`.
    """

    def __init__(self, domain_min_m=(0.0, 0.0, 0.0), domain_max_m=(1.0, 1.0, 1.0),
                 periodic=(False, False, False), gravity_m_s2=(0.0, 0.0, -9.81), *,
                 neighbor_skin_m: float | None = None, sort_every: int = 10,
                 n_chunks: int | None = None, max_contacts_per_particle: int = 16,
                 max_geometry_contacts: int = 8, parallel_min_particles: int = 1000,
                 event_buffer_rows: int = 4096, parallel: bool | None = None,
                 backend: str = "cpu") -> None:
        self._backend = check_backend(backend)
        self._step_fn = None  # the backend's step loop (backend.stepper), made at the first run
        # Warp backends: the state, the step and the rebuild on the Warp device (DeviceEngine,
        # made at the first rebuild); False: numba rebuilds, the step loop through _step_fn
        self._on_device = self._backend != "cpu"
        self._dev = None
        self._lo = vec3("domain_min_m", domain_min_m)
        self._hi = vec3("domain_max_m", domain_max_m)
        if np.any(self._hi <= self._lo):
            raise MsmillInputError("domain_max_m", domain_max_m, "every component > domain_min_m")
        try:
            per = [bool(p) for p in periodic]
        except TypeError:
            per = []
        if len(per) != 3:
            raise MsmillInputError("periodic", periodic, "three booleans")
        self._periodic = np.array(per, np.int8)
        self._gravity = vec3("gravity_m_s2", gravity_m_s2)
        self._skin = (None if neighbor_skin_m is None
                      else _pos_number("neighbor_skin_m", neighbor_skin_m))
        if int(sort_every) < 1:
            raise MsmillInputError("sort_every", sort_every, "an integer >= 1")
        self._sort_every = int(sort_every)
        self._ggrid = None
        import numba

        self._nch = int(n_chunks) if n_chunks else 4 * numba.get_num_threads()
        if self._nch < 1:
            raise MsmillInputError("n_chunks", n_chunks, "an integer >= 1")
        self._par_min = int(parallel_min_particles)
        self._cells_n = 0  # particle count the cell grid was sized for
        self._par_mode = None if parallel is None else bool(parallel)
        self._last_par = False  # kind of the last step-kernel call (rebuilds follow it)
        self._perf: dict[bool, float | None] = {True: None, False: None}
        self._calls = 0
        self._tuned_mode: bool | None = None  # kind of the last timed call (see _tune)
        self._smax = int(max_contacts_per_particle)
        self._sgmax = int(max_geometry_contacts)
        if self._smax < 1 or self._sgmax < 1:
            raise MsmillInputError("max_contacts_per_particle", (self._smax, self._sgmax),
                                   "integers >= 1")
        self._materials: list[dict] = []
        self._mat_index: dict[str, int] = {}
        self._interactions: dict[tuple[int, int], dict] = {}
        self._geoms: list[dict] = []
        self._sources: list[dict] = []
        self._sinks: list[dict] = []
        self._time = 0.0
        self._dt: float | None = None
        self._next_id = 0
        self._pd = self._empty_particles()  # the particle arrays (read them through _p)
        if int(event_buffer_rows) < 8:
            raise MsmillInputError("event_buffer_rows", event_buffer_rows, "an integer >= 8")
        self._rec = EventRecorder(self._nch, int(event_buffer_rows))
        self._removed: list[dict[str, np.ndarray]] = []
        self._ts: list[tuple] = []
        self._snaps: list[tuple[float, pd.DataFrame]] = []
        self._mass_out = 0.0
        self._n_lost = 0
        self._dirty = True  # geometry/material tables need packing
        self._need_rebuild = True
        self._frc_stale = False  # frc/trq lag the last force pass (_settle_forces)
        self._n_rebuilds = 0
        self._maxn = 16
        self._maxg = 4
        self._disp = np.zeros(1)  # displacement bound since the last neighbour build (m)
        self._warned: set[str] = set()
        self.stats = {"rebuilds": 0, "steps": 0, "loop_time_s": 0.0}
        self._stamp = 0  # steps run, stamps the partner shares (kernels.advance)

    # ------------------------------------------------------------------ checkpoints
    def __getstate__(self) -> dict[str, Any]:
        # the slot-field views alias the slot records: pickled, they would become copies the kernels
        # write while the records (which _keep permutes) stay behind; they are bound again on load
        if self._dev is not None:
            self._host_view(lists=True)  # everything, lists included, as the numba engine keeps it
        state = self.__dict__.copy()
        state["_step_fn"] = None  # a Warp backend's device state is made again after loading
        state["_dev"] = None
        state["_p"] = {k: v for k, v in state.pop("_pd").items() if k not in _SLOT_VIEWS}
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        state.setdefault("_backend", "cpu")  # checkpoints written before the backends
        state.setdefault("_step_fn", None)
        state.setdefault("_on_device", state["_backend"] != "cpu")
        state["_dev"] = None
        state["_pd"] = state.pop("_p")
        self.__dict__.update(state)
        _slot_views(self._pd)

    @property
    def _p(self) -> dict[str, np.ndarray]:
        """The particle arrays, up to date, for reading and writing (a Warp device's copy is then stale)."""
        p = self._host_view()
        if self._dev is not None:
            self._dev.dev_ok = False
        return p

    def _host_view(self, lists: bool = False) -> dict[str, np.ndarray]:
        """The particle arrays (and events, geometry poses; ``lists``: the lists), up to date, to read only."""
        if self._dev is not None:
            self._settle_forces()
            self._dev.to_host(self, lists)
        return self._pd

    def append_only_lists(self) -> dict[str, list]:
        """The run's records that only ever grow (finished events, removed particles, time series,
        snapshots): a checkpoint writes each item once (:mod:`msmill.dem.checkpoint`)."""
        self._host_view()
        return {**self._rec.append_only_lists(), "removed": self._removed, "timeseries": self._ts,
                "snapshots": self._snaps}

    # ------------------------------------------------------------------ declaration
    def add_material(self, name: str, *, youngs_modulus_pa: float, poisson_ratio: float,
                     density_kg_m3: float) -> int:
        """Declare a material; ``youngs_modulus_pa=inf`` makes a rigid wall material.

        Returns
        -------
        int
            Material index.
        """
        if not isinstance(name, str) or not name:
            raise MsmillInputError("material name", name, "a non-empty string")
        if name in self._mat_index:
            raise MsmillInputError("material name", name, "a name not declared before")
        e = _pos_number("youngs_modulus_pa", youngs_modulus_pa, allow_inf=True)
        nu = float(poisson_ratio)
        if not (-1.0 < nu < 0.5):
            raise MsmillInputError("poisson_ratio", poisson_ratio, "a number in (-1, 0.5)")
        rho = _pos_number("density_kg_m3", density_kg_m3)
        self._mat_index[name] = len(self._materials)
        self._materials.append({"name": name, "E": e, "nu": nu, "rho": rho})
        self._dirty = True
        return self._mat_index[name]

    def _mat(self, name: str) -> int:
        if name not in self._mat_index:
            raise MsmillInputError("material", name, f"one of {sorted(self._mat_index)}")
        return self._mat_index[name]

    def set_interaction(self, material_a: str, material_b: str, *, restitution: float,
                        friction: float, tangential_damping: float | None = None) -> None:
        """Set restitution and friction of a material pair (order-free).

        ``tangential_damping`` is ``eta_tau`` of paper Eq. 10 (default: equal
        to the calibrated ``eta_H``).
        """
        a, b = self._mat(material_a), self._mat(material_b)
        e = float(restitution)
        if not (0.0 < e <= 1.0):
            raise MsmillInputError("restitution", restitution, "a number in (0, 1]")
        mu = float(friction)
        if not (mu >= 0.0 and math.isfinite(mu)):
            raise MsmillInputError("friction", friction, "a finite number >= 0")
        if tangential_damping is not None:
            tangential_damping = _pos_number("tangential_damping", tangential_damping,
                                             allow_zero=True)
        self._interactions[(min(a, b), max(a, b))] = {
            "restitution": e, "friction": mu, "tangential_damping": tangential_damping}
        self._dirty = True

    def _add_geom(self, kind: int, ref: np.ndarray, material: str, tag: str, group: int,
                  rotation: Rotation | None, thickness: float) -> int:
        if rotation is not None and not isinstance(rotation, Rotation):
            raise MsmillInputError("rotation", rotation, "a msmill.dem.Rotation or None")
        if not isinstance(tag, str):
            raise MsmillInputError("tag", tag, "a string")
        rot = rotation.row() if rotation is not None else np.zeros(8)
        row = np.zeros(NG)
        row[: ref.size] = ref
        gid = len(self._geoms)
        self._geoms.append({"kind": kind, "ref": row, "rot": rot, "mat": self._mat(material),
                            "tag": tag, "group": int(group), "thickness": thickness})
        self._dirty = True
        self._need_rebuild = True
        return gid

    def add_plane(self, point_m, normal, *, material: str, tag: str = "plane", group: int = 0,
                  rotation: Rotation | None = None) -> int:
        """Infinite plane; particles live on the side ``normal`` points to. Returns the geom id."""
        ref = np.concatenate([vec3("point_m", point_m), vec3("normal", normal, unit=True)])
        return self._add_geom(PLANE, ref, material, tag, group, rotation, np.inf)

    def add_box(self, center_m, half_extents_m, axes=None, *, material: str, tag: str = "box",
                group: int = 0, rotation: Rotation | None = None) -> int:
        """Oriented box (solid); rows of ``axes`` are its local x, y, z axes. Returns the geom id.

        A zero half extent gives a finite plate of zero thickness.
        """
        h = vec3("half_extents_m", half_extents_m)
        if np.any(h < 0):
            raise MsmillInputError("half_extents_m", half_extents_m, "three numbers >= 0")
        ax = orthonormal_axes("axes", axes)
        ref = np.concatenate([vec3("center_m", center_m), ax.ravel(), h])
        return self._add_geom(BOX, ref, material, tag, group, rotation, 2 * float(h.min()))

    def add_plate(self, center_m, half_size_m, axes=None, *, thickness_m: float = 0.0,
                  material: str, tag: str = "plate", group: int = 0,
                  rotation: Rotation | None = None) -> int:
        """Finite plate in the local x-y plane of ``axes`` (a thin box). Returns the geom id."""
        hs = np.asarray(half_size_m, float).reshape(-1)
        if hs.size != 2 or np.any(~np.isfinite(hs)) or np.any(hs <= 0):
            raise MsmillInputError("half_size_m", half_size_m, "two numbers > 0")
        t = _pos_number("thickness_m", thickness_m, allow_zero=True)
        return self.add_box(center_m, (hs[0], hs[1], 0.5 * t), axes, material=material, tag=tag,
                            group=group, rotation=rotation)

    def add_cylinder(self, p0_m, p1_m, radius_m: float, *, material: str, tag: str = "cylinder",
                     group: int = 0, rotation: Rotation | None = None,
                     inside: bool = False) -> int:
        """Finite cylinder from ``p0_m`` to ``p1_m``. Returns the geom id.

        ``inside=False``: solid capped cylinder (hub, shaft), particles outside.
        ``inside=True``: open tube, particles inside (liner, drum).
        """
        p0 = vec3("p0_m", p0_m)
        p1 = vec3("p1_m", p1_m)
        ln = float(np.linalg.norm(p1 - p0))
        if ln <= 0:
            raise MsmillInputError("p1_m", p1_m, "a point different from p0_m")
        rc = _pos_number("radius_m", radius_m)
        ref = np.concatenate([p0, (p1 - p0) / ln, [ln, rc, 1.0 if inside else 0.0]])
        return self._add_geom(CYL, ref, material, tag, group, rotation, np.inf)

    def add_particles(self, positions_m, radii_m, velocities_m_s=None, *, material: str,
                      angular_velocities_rad_s=None) -> np.ndarray:
        """Add particles (no overlap check). Returns their ids (int64)."""
        pos = np.asarray(positions_m, float)
        if pos.ndim == 1 and pos.size == 3:
            pos = pos.reshape(1, 3)
        if pos.ndim != 2 or pos.shape[1] != 3 or not np.all(np.isfinite(pos)):
            raise MsmillInputError("positions_m", positions_m, "an (n, 3) array of finite numbers")
        n = pos.shape[0]
        rad = np.broadcast_to(np.asarray(radii_m, float), (n,)).copy() if n else np.zeros(0)
        if n and (not np.all(np.isfinite(rad)) or np.any(rad <= 0)):
            raise MsmillInputError("radii_m", radii_m, "finite numbers > 0")
        vel = self._vec_array("velocities_m_s", velocities_m_s, n)
        omg = self._vec_array("angular_velocities_rad_s", angular_velocities_rad_s, n)
        return self._append(pos, rad, vel, omg, self._mat(material))

    @staticmethod
    def _vec_array(name: str, value, n: int) -> np.ndarray:
        if value is None:
            return np.zeros((n, 3))
        try:
            v = np.broadcast_to(np.asarray(value, float), (n, 3)).copy()
        except ValueError:
            raise MsmillInputError(name, value, "an (n, 3) array or one 3-vector") from None
        if not np.all(np.isfinite(v)):
            raise MsmillInputError(name, value, "finite numbers")
        return v

    def add_source(self, region_min_m, region_max_m, mass_flow_kg_s: float, *, radii_m,
                   velocity_m_s=(0.0, 0.0, 0.0), material: str, start_s: float = 0.0,
                   stop_s: float | None = None, seed: int = 0,
                   insert_interval_s: float = 1e-3, n_tries: int = 50) -> int:
        """Insert particles at ``mass_flow_kg_s`` without overlap in a box region.

        Parameters
        ----------
        radii_m : float, array or (values, weights)
            A fixed radius, an empirical sample drawn from uniformly, or values
            with number weights (m).
        insert_interval_s : float
            Particles are inserted in batches at this interval (s); the mass
            owed accumulates, so the mean rate is exact.
        """
        lo = vec3("region_min_m", region_min_m)
        hi = vec3("region_max_m", region_max_m)
        if np.any(hi <= lo):
            raise MsmillInputError("region_max_m", region_max_m, "every component > region_min_m")
        rate = _pos_number("mass_flow_kg_s", mass_flow_kg_s)
        if isinstance(radii_m, tuple) and len(radii_m) == 2:
            vals = np.asarray(radii_m[0], float).reshape(-1)
            w = np.asarray(radii_m[1], float).reshape(-1)
            if vals.size != w.size or np.any(w < 0) or w.sum() <= 0:
                raise MsmillInputError("radii_m", radii_m, "(values, weights) of equal length, "
                                                           "weights >= 0 with positive sum")
            w = w / w.sum()
        else:
            vals = np.asarray(radii_m, float).reshape(-1)
            w = np.full(vals.size, 1.0 / max(vals.size, 1))
        if vals.size == 0 or not np.all(np.isfinite(vals)) or np.any(vals <= 0):
            raise MsmillInputError("radii_m", radii_m, "radii > 0 (m)")
        if np.any(2 * vals.max() >= hi - lo):
            raise MsmillInputError("radii_m", float(vals.max()), "a diameter smaller than the "
                                                                 "source region")
        stop = np.inf if stop_s is None else float(stop_s)
        mi = self._mat(material)
        self._sources.append({
            "lo": lo, "hi": hi, "rate": rate, "vals": vals, "w": w,
            "vel": vec3("velocity_m_s", velocity_m_s), "mat": mi,
            "start": float(start_s), "stop": stop, "rng": np.random.default_rng(seed),
            "interval": _pos_number("insert_interval_s", insert_interval_s),
            "tries": int(n_tries), "debt": 0.0, "last": float(start_s),
            "next": float(start_s), "pending": None, "inserted_kg": 0.0})
        return len(self._sources) - 1

    def add_sink(self, region_min_m, region_max_m, *, tag: str = "outlet") -> int:
        """Delete particles whose centre enters the box region; recorded in :meth:`removed`."""
        lo = vec3("region_min_m", region_min_m)
        hi = vec3("region_max_m", region_max_m)
        if np.any(hi <= lo):
            raise MsmillInputError("region_max_m", region_max_m, "every component > region_min_m")
        self._sinks.append({"lo": lo, "hi": hi, "tag": str(tag)})
        return len(self._sinks) - 1

    # ------------------------------------------------------------------ particle storage
    def _empty_particles(self) -> dict[str, np.ndarray]:
        p: dict[str, np.ndarray] = {k: np.zeros((0, 3)) for k in _P_FLOAT3}
        p.update({k: np.zeros(0) for k in _P_SCALAR})
        p["mat"] = np.zeros(0, np.int32)
        p["pid"] = np.zeros(0, np.int64)
        p["flag"] = np.zeros(0, np.int32)
        s, sg = self._smax, self._sgmax
        p["h_rec"] = np.zeros((0, s), _SLOT_REC["h"])
        p["h_n"] = np.zeros(0, np.int32)
        p["g_rec"] = np.zeros((0, sg), _SLOT_REC["g"])
        p["g_n"] = np.zeros(0, np.int32)
        _slot_views(p)
        return p

    def _append(self, pos, rad, vel, omg, mat: int) -> np.ndarray:
        n = pos.shape[0]
        rho = self._materials[mat]["rho"]
        mass = rho * 4.0 / 3.0 * np.pi * rad**3
        new = {k: v for k, v in self._empty_particles().items() if k not in _SLOT_VIEWS}
        for k, v in new.items():
            new[k] = np.zeros((n, *v.shape[1:]), v.dtype)
        new["pos"] = pos.copy()
        new["vel"] = vel
        new["omg"] = omg
        new["rad"] = rad
        new["mass"] = mass
        new["invm"] = 1.0 / mass
        new["invi"] = 1.0 / (0.4 * mass * rad**2)
        new["mat"][:] = mat
        ids = np.arange(self._next_id, self._next_id + n, dtype=np.int64)
        self._next_id += n
        new["pid"] = ids
        for k in ("h_rec", "g_rec"):
            new[k]["ev"] = -1
        for k in new:
            self._p[k] = np.concatenate([self._p[k], new[k]])
        _slot_views(self._p)
        self._need_rebuild = True
        return ids

    def _keep(self, keep: np.ndarray) -> None:
        """Reorder / compact every per-particle array (boolean mask or index array)."""
        self._settle_forces()
        p = self._p
        idx = np.nonzero(keep)[0] if keep.dtype == np.bool_ else np.asarray(keep, np.int64)
        for pre in _SLOTS:
            rec = p[f"{pre}_rec"]
            nw = rec.dtype.itemsize // 8
            words = rec.view(np.int64).reshape(rec.shape[0], rec.shape[1], nw)
            out = K.permute_slot_records(idx, p[f"{pre}_n"], words)
            p[f"{pre}_rec"] = out.reshape(out.shape[0], rec.shape[1] * nw).view(rec.dtype)
        for k in p:
            if k not in _SLOT_VIEWS and k not in ("h_rec", "g_rec"):
                p[k] = p[k][idx]
        _slot_views(p)

    # ------------------------------------------------------------------ packing
    def _pack(self) -> None:
        if not self._materials:
            raise MsmillInputError("materials", [], "at least one add_material() call")
        self._ptab = pair_table(self._materials, self._interactions)
        g = self._geoms
        self._gref = np.array([x["ref"] for x in g]).reshape(len(g), NG)
        self._grot = np.array([x["rot"] for x in g]).reshape(len(g), 8)
        self._gkind = np.array([x["kind"] for x in g], np.int32)
        self._gmat = np.array([x["mat"] for x in g], np.int32)
        self._gbound = np.array([bound_row(x["kind"], x["ref"], x["rot"]) for x in g]
                                ).reshape(len(g), 6)
        self._gcur = self._gref.copy()
        K.update_geometry(self._gref, self._grot, self._gkind, 0.0, self._gcur)
        # along a periodic axis a primitive is met through its periodic images unless it is
        # continuous along the axis (geometry.spans_axis)
        L = self._hi - self._lo
        self._gaabb = np.array([np.concatenate(K._geom_aabb(k, self._gcur, self._grot, self._gkind,
                                                            self._gbound)) for k in range(len(g))]
                               ).reshape(len(g), 6)
        self._gspan = np.array([[1 if not self._periodic[a] else
                                 int(spans_axis(x["kind"], x["ref"], x["rot"], a, float(L[a])))
                                 for a in range(3)] for x in g], np.int8).reshape(len(g), 3)
        # bounding box of the imaged primitives per axis: a shifted candidate test is only tried near it
        self._img_box = np.array([np.inf] * 3 + [-np.inf] * 3)
        for a in range(3):
            im = self._gspan[:, a] == 0
            if im.any():
                self._img_box[a] = self._gaabb[im, a].min()
                self._img_box[3 + a] = self._gaabb[im, 3 + a].max()
        self._ggrid = None
        self._sinkbox = np.array([np.concatenate([s["lo"], s["hi"]]) for s in self._sinks]
                                 ).reshape(len(self._sinks), 6)
        self._dirty = False

    def _r_min_max(self) -> tuple[float, float]:
        radii = [self._pd["rad"]] + [s["vals"] for s in self._sources]
        allr = np.concatenate(radii) if radii else np.zeros(0)
        if allr.size == 0:
            return math.nan, math.nan
        return float(allr.min()), float(allr.max())

    def _wall_speed_max(self) -> float:
        v = 0.0
        for k, g in enumerate(self._geoms):
            if g["rot"][7] > 0:
                rmax = self._gbound[k, 1]
                if not math.isfinite(rmax):
                    rmax = float(np.max(np.abs(self._hi - self._lo))) * 2
                v = max(v, abs(g["rot"][6]) * rmax)
        return v

    def contact_time_s(self, max_relative_speed_m_s: float) -> float:
        """Smallest Hertz contact time over all pairs at the given impact speed (s)."""
        v = _pos_number("max_relative_speed_m_s", max_relative_speed_m_s)
        if self._dirty:
            self._pack()
        mats = {int(m) for m in np.unique(self._pd["mat"])} | {s["mat"] for s in self._sources}
        rmin = {}
        for m in mats:
            rs = [self._pd["rad"][self._pd["mat"] == m]] + [s["vals"] for s in self._sources
                                                          if s["mat"] == m]
            rmin[m] = float(np.concatenate(rs).min())
        tc = math.inf
        for a in mats:
            ma = self._materials[a]["rho"] * 4 / 3 * np.pi * rmin[a] ** 3
            for b in mats:
                mb = self._materials[b]["rho"] * 4 / 3 * np.pi * rmin[b] ** 3
                tc = min(tc, hertz_contact_time(ma * mb / (ma + mb),
                                                rmin[a] * rmin[b] / (rmin[a] + rmin[b]),
                                                self._ptab[a, b, 5], v))
            for gm in {g["mat"] for g in self._geoms}:
                tc = min(tc, hertz_contact_time(ma, rmin[a], self._ptab[a, gm, 5], v))
        return tc

    def _parallel(self) -> bool:
        if self.n_particles < self._par_min:
            return False
        if not threads_usable():
            self._warn_once("fork", "this process was forked from one running numba's OpenMP threads, "
                                    "which is not fork-safe: the DEM runs its serial kernels here "
                                    "(start worker processes with 'spawn' to use threads)")
            return False
        return True

    def _choose_parallel(self) -> bool:
        """Threaded or serial step kernels for the next call (results are identical).

        ``parallel=None`` (auto): above ``parallel_min_particles`` both are
        timed and the faster one is used, re-probing the threads every 32
        calls while the serial kernels are faster (on a shared machine the
        threaded passes can be slower) and the serial kernels every 256 calls
        while the threads are faster.
        """
        if not self._parallel():
            return False
        if self._par_mode is not None:
            return self._par_mode
        perf = self._perf
        for mode in (True, False):
            if perf[mode] is None:
                return mode
        self._calls += 1
        best = perf[True] <= perf[False]
        # re-probe the slower kind: the threads every 32 calls while the serial kernels are
        # faster (the other tenants may have left the cores), the serial kernels only every
        # 256 calls while the threads are faster (a slowed-down threaded call shows in the
        # threads' own timing, and each serial probe costs a call, and the rebuild after it,
        # at the serial speed: ~6 % of the gas benchmark at phi = 0.05 with every 32)
        every = 256 if best else 32
        return (not best) if self._calls % every == 0 else best

    def _tune(self, mode: bool, elapsed: float, steps: int) -> None:
        if steps < 5 or self.n_particles == 0:
            return
        cost = elapsed / (steps * self.n_particles)
        old = self._perf[mode]
        # a probe (the other kind than last time) replaces its kind's stale estimate: averaged
        # with it, one slow first threaded call (thread start-up, a busy minute) kept the
        # serial kernels in use for several re-probes
        probe = mode != self._tuned_mode
        self._tuned_mode = mode
        self._perf[mode] = cost if old is None or probe else 0.5 * old + 0.5 * cost

    # ------------------------------------------------------------------ rebuild
    def _cells(self, rmax: float) -> None:
        L = self._hi - self._lo
        cut = 2 * rmax + self._skin
        nc = np.maximum(np.floor(L / cut).astype(np.int64), 1)
        # Every rebuild zeroes and prefix-sums the whole cell grid, so its size
        # follows the particle count (a sparse mill slice would otherwise sweep
        # ~1e5 empty cells per rebuild). Coarsen the longest axis first; cells
        # only grow, so they stay >= the cut-off.
        n = len(self._pd["rad"])
        cap = max(4096, CELLS_PER_PARTICLE * n)
        while np.prod(nc) > cap:
            a = int(np.argmax(nc))
            floor = 3 if self._periodic[a] else 1
            if nc[a] <= floor:
                break
            nc[a] = max(nc[a] // 2, floor)
        self._cells_n = n
        for a in range(3):
            if self._periodic[a] and nc[a] < 3:
                raise MsmillInputError(
                    "domain_max_m", tuple(self._hi),
                    f"a periodic length along axis {a} of at least 3 x (2 r_max + skin) "
                    f"= {3 * cut:.4g} m")
        self._ncell = nc
        self._cell_len = L / nc
        self._box_len = L.copy()

    def _settle_forces(self) -> None:
        """Bring ``frc``/``trq`` up to the last force pass (the passes skip particles out of contact).

        Needs the kinds and partner shares of that pass: call before they are
        replaced (rebuild) or the particles reordered.
        """
        if self._frc_stale and self._dev is not None:
            self._frc_stale = False
            self._dev.settle(self)
        elif self._frc_stale:
            p = self._pd
            K.settle_forces(self._kind, p["mass"], self._gravity, p["frc"], p["trq"], self._pair[3],
                            self._stamp)
            self._frc_stale = False

    def _resize_cells(self) -> None:
        """Coarser cells for a larger radius, finer ones for a grown population (``_cells``)."""
        rad = self._pd["rad"]
        rmax = float(rad.max()) if rad.size else 0.0
        if rmax > self._rmax_cells:
            self._rmax_cells = rmax
            self._cells(rmax)
        elif rad.size > 2 * max(self._cells_n, 512):  # population grew: finer cells pay off
            self._cells(self._rmax_cells)

    def _geometry_grid(self) -> None:
        """Poses at the rebuild's time; the coarse geometry grid again if the cut-off changed."""
        K.update_geometry(self._gref, self._grot, self._gkind, self._time, self._gcur)
        margin = self._rmax_cells + self._skin
        if getattr(self, "_ggrid_margin", None) != margin or self._ggrid is None:
            L = self._hi - self._lo
            size = float(L.max()) / GEOM_CELLS_LONG_AXIS
            self._gnc = np.clip(np.ceil(L / size), 1, GEOM_CELLS_LONG_AXIS).astype(np.int64)
            self._gcl = L / self._gnc
            self._ggrid = K.build_geom_grid(self._gcur, self._grot, self._gkind, self._gbound,
                                            self._lo, self._gcl, self._gnc, margin)
            self._ggrid_margin = margin

    def _rebuild(self) -> None:
        if self._on_device:
            self._rebuild_on_device()
            return
        self._settle_forces()
        p = self._p
        K.wrap_positions(p["pos"], self._lo, self._box_len, self._periodic, p["g_gid"], p["g_n"],
                         self._gspan)
        self._resize_cells()
        _cell, start, order, cell = K.bin_cells(p["pos"], self._lo, self._cell_len, self._ncell)
        par = self._last_par and threads_usable()  # rebuilds follow the step kernels' choice
        if self._n_rebuilds % self._sort_every == 0 and p["pos"].shape[0] > 0:
            self._keep(order)
            cell = cell[order]  # cell coordinates (n, 3)
            order = np.arange(cell.shape[0], dtype=np.int64)
        self._nb = K.build_neighbours(p["pid"], p["pos"], p["rad"], self._skin, cell, start, order,
                                      self._ncell, self._periodic, self._box_len,
                                      par, self._maxn)
        self._maxn = int(self._nb[5] * 1.25) + 4
        m = self._nb[1].shape[0]
        # partner shares in reverse-list order, stamped with the step that wrote them
        # (the fourth: the step in which each particle last got a partner share)
        self._pair = (np.zeros(m, np.int64), np.zeros((m, 3)), np.zeros((m, 3)),
                      np.zeros(p["pos"].shape[0], np.int64))
        self._geometry_grid()
        self._gc = K.build_geom_candidates(p["pos"], p["rad"], self._skin, self._gcur,
                                           self._grot, self._gkind, self._gbound, self._gspan,
                                           self._periodic, self._box_len, self._img_box, self._lo,
                                           self._gcl, self._gnc, self._ggrid[0], self._ggrid[1],
                                           par, self._maxg)
        self._maxg = int(self._gc[2] * 1.25) + 2
        self._kind = K.particle_kinds(self._nb[0], self._nb[2], self._nb[3], self._gc[0], p["h_n"], p["g_n"],
                                      p["vel"], p["omg"])
        self._work = K.work_lists(self._kind, self._nch)
        self._disp[0] = 0.0
        self._rebuilt()

    def _rebuilt(self) -> None:
        self._n_rebuilds += 1
        self.stats["rebuilds"] += 1
        self._need_rebuild = False

    def _rebuild_on_device(self) -> None:
        """The rebuild of a Warp backend, on its device (:class:`msmill.dem.warp_rebuild.DeviceEngine`)."""
        self._device()
        self._settle_forces()
        self._resize_cells()
        self._geometry_grid()
        sort = self._n_rebuilds % self._sort_every == 0 and self.n_particles > 0
        self._dev.rebuild(self, sort)
        self._rebuilt()

    def _device(self):
        """The Warp backend's :class:`~msmill.dem.warp_rebuild.DeviceEngine`, made at first use."""
        if self._dev is None:
            self._dev = device_engine(self._backend)
        return self._dev

    # ------------------------------------------------------------------ removal / insertion
    def _handle_flags(self) -> None:
        p = self._p
        flag = p["flag"]
        bad = flag == K.F_NONFINITE
        if bad.any():
            k = int(np.nonzero(bad)[0][0])
            raise DemRuntimeError(
                f"non-finite position or velocity of particle {int(p['pid'][k])} at "
                f"t = {p['flag_t'][k]:.6g} s; reduce dt_s or increase safety margins")
        gone = flag != K.F_OK
        if not gone.any():
            return
        tags = np.array(["lost"] + [s["tag"] for s in self._sinks], dtype=object)
        code = np.where(flag[gone] == K.F_LOST, 0, flag[gone] - 1)
        rec = {"particle_id": p["pid"][gone].copy(), "time_s": p["flag_t"][gone].copy(),
               "radius_m": p["rad"][gone].copy(), "mass_kg": p["mass"][gone].copy(),
               "tag": tags[code]}
        self._removed.append(rec)
        lost = int((flag[gone] == K.F_LOST).sum())
        self._mass_out += float(p["mass"][gone][flag[gone] >= 2].sum())
        if lost:
            self._n_lost += lost
            warnings.warn(f"{lost} particle(s) left the non-periodic domain and were deleted "
                          f"(total lost {self._n_lost}); see removed(), tag 'lost'",
                          DemRuntimeWarning, stacklevel=3)
        # close events whose owner disappears
        for ev, pk, ds, cnt in (("h_ev", "h_pk", "h_ds", "h_n"), ("g_ev", "g_pk", "g_ds", "g_n")):
            refs = p[ev][gone]
            used = np.arange(refs.shape[1])[None, :] < p[cnt][gone][:, None]
            m = (refs >= 0) & used
            if m.any():
                tt = np.broadcast_to(p["flag_t"][gone][:, None], refs.shape)[m]
                r = refs[m]
                nch = self._nch
                self._rec.evf[r % nch, r // nch, K.EV_END] = tt
                self._rec.evf[r % nch, r // nch, K.EV_PEAK] = p[pk][gone][m]
                self._rec.evf[r % nch, r // nch, K.EV_DISS] = p[ds][gone][m]
        self._keep(~gone)
        self._need_rebuild = True

    def _insert_sources(self) -> None:
        t = self._time
        for s in self._sources:
            if t < s["next"] or t < s["start"]:
                continue
            s["next"] = t + s["interval"]
            t_end = min(t, s["stop"])
            if t_end > s["last"]:
                s["debt"] += s["rate"] * (t_end - s["last"])
                s["last"] = t_end
            rho = self._materials[s["mat"]]["rho"]
            mean_m = rho * 4 / 3 * np.pi * float(np.sum(s["w"] * s["vals"] ** 3))
            nmax = int(s["debt"] / mean_m * 1.5) + 4
            draw = s["rng"].choice(s["vals"], size=nmax, p=s["w"])
            if s["pending"] is not None:
                draw[0] = s["pending"]
            masses = rho * 4 / 3 * np.pi * draw**3
            cum = np.cumsum(masses)
            n = int(np.searchsorted(cum, s["debt"], side="right"))
            n = min(n, nmax - 1)
            s["pending"] = draw[n]
            if n == 0:
                continue
            radii = draw[:n]
            lo, hi = s["lo"], s["hi"]
            u = s["rng"].random((n, s["tries"], 3))
            cand = lo + radii[:, None, None] + u * (hi - lo - 2 * radii[:, None, None])
            p = self._host_view()
            pos = p["pos"]
            reach = float(radii.max()) + (float(p["rad"].max()) if pos.size else 0.0)
            inside = (pos >= lo - reach) & (pos <= hi + reach)
            inside[:, self._periodic.astype(bool)] = True  # periodic images may reach the region
            near = np.all(inside, axis=1)
            out, ok = K.place_without_overlap(cand, radii, pos[near], p["rad"][near],
                                              self._box_len, self._periodic)
            placed = masses[:n][ok].sum()
            s["debt"] -= masses[:n].sum()
            s["debt"] += masses[:n][~ok].sum()
            s["inserted_kg"] += placed
            if (~ok).any() and s["debt"] > 20 * s["rate"] * s["interval"] + masses.max():
                self._warn_once("source_backlog", "a source cannot place its particles without "
                                "overlap; the inserted mass flow falls short (enlarge the region)")
            if ok.any():
                nn = int(ok.sum())
                self._append(out[ok], radii[ok].copy(), np.tile(s["vel"], (nn, 1)),
                             np.zeros((nn, 3)), s["mat"])

    def _warn_once(self, key: str, msg: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            warnings.warn(msg, DemRuntimeWarning, stacklevel=4)

    # ------------------------------------------------------------------ run
    def run(self, duration_s: float, dt_s: float | None = None, *,
            max_relative_speed_m_s: float = 60.0, safety: float = 0.2,
            snapshot_every_s: float | None = None, progress: bool = True,
            callback: Callable[[Simulation], bool | None] | None = None,
            callback_every: int = 1000, timeseries_every_s: float | None = None,
            max_overlap_fraction: float = 0.05, travel_fraction: float = 0.1,
            snapshot_times_s=None) -> int:
        """Advance the simulation by ``duration_s``; may be called repeatedly.

        Parameters
        ----------
        duration_s : float
            Simulated time to run (s).
        dt_s : float, optional
            Time step (s). Default: ``safety`` x the smallest Hertz contact
            time at ``max_relative_speed_m_s`` (see :meth:`contact_time_s`),
            further limited so that the travel per step at that speed (or at
            the fastest wall, if faster) is at most ``travel_fraction`` of the
            smallest radius and of the thinnest plate.
        max_relative_speed_m_s : float
            Highest expected relative impact speed, e.g. the rotor tip speed
            plus the feed speed (m/s).
        safety : float
            Fraction of the contact time used as step.
        snapshot_every_s : float, optional
            Take a :meth:`snapshot` at the times ``k * snapshot_every_s`` (s),
            at the first step at or after each.
        snapshot_times_s : sequence of float, optional
            Also take snapshots at these absolute times (s) within this run
            (each at the first step at or after the time).
        progress : bool
            Show a Rich progress bar.
        callback : callable, optional
            ``callback(sim)`` every ``callback_every`` steps; returning True
            stops the run early (e.g. at steady state).
        timeseries_every_s : float, optional
            Time-series sampling interval (s); default ``duration_s / 200`` but
            at least 500 steps.
        max_overlap_fraction : float
            Warn when an overlap exceeds this fraction of the smaller radius.
        travel_fraction : float
            Allowed travel per step as a fraction of the smallest radius / plate.

        Returns
        -------
        int
            Number of steps run.
        """
        duration = _pos_number("duration_s", duration_s, allow_zero=True)
        cb_every = int(callback_every)
        if cb_every < 1:
            raise MsmillInputError("callback_every", callback_every, "an integer >= 1")
        dt, lmin = self._prepare_run(max_relative_speed_m_s, safety, dt_s, travel_fraction)
        nsteps = round(duration / dt)
        t_start = self._time
        sched = _Schedule.start(self, t_start, dt, duration, timeseries_every_s, snapshot_every_s, snapshot_times_s)
        wall_v = self._wall_speed_max()
        bar = task = None
        if progress:
            from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

            bar = Progress(TextColumn("DEM t={task.fields[t]:.4f} s n={task.fields[n]}"),
                           BarColumn(), TimeRemainingColumn())
            bar.start()
            task = bar.add_task("dem", total=nsteps, t=self._time, n=self.n_particles)
        done = 0
        diag = np.zeros((self._nch, K.N_DIAG))
        last_cb = 0
        stopped = False
        try:
            while done < nsteps:
                if self._sources:
                    self._insert_sources()
                if self._need_rebuild:
                    self._rebuild()
                sched.record_due(self, dt)
                limit = sched.steps_to_next(self, dt, nsteps - done)
                if callback is not None:
                    limit = min(limit, max(1, cb_every - (done - last_cb)))
                k, reason = self._advance(dt, limit, diag)
                self.stats["steps"] += k
                self._stamp += k
                done += k
                self._time = t_start + done * dt
                self._check_diag(diag, dt, max_overlap_fraction, travel_fraction, lmin, wall_v)
                if reason == K.R_FLAGGED:
                    self._handle_flags()
                elif reason == K.R_REBUILD:
                    self._need_rebuild = True
                elif reason == K.R_EVFULL:
                    self._flush_events()
                if bar is not None:
                    bar.update(task, completed=done, t=self._time, n=self.n_particles)
                if callback is not None and done - last_cb >= cb_every:
                    last_cb = done
                    if callback(self):
                        stopped = True
                        break
        finally:
            if bar is not None:
                bar.stop()
        if not stopped or self._time >= sched.next_ts - 0.5 * dt:
            self._record_ts()
        return done

    def _prepare_run(self, max_relative_speed_m_s: float, safety: float, dt_s: float | None,
                     travel_fraction: float) -> tuple[float, float]:
        """Check the step arguments, pack the particles, size the cells; ``(dt_s, smallest radius/plate m)``."""
        vrel = _pos_number("max_relative_speed_m_s", max_relative_speed_m_s)
        safety = _pos_number("safety", safety)
        if safety > MAX_SAFETY:
            raise MsmillInputError(
                "safety", safety,
                f"a number in (0, {MAX_SAFETY}] (fraction of the Hertz contact time; above it the "
                "explicit step misses the damped contact: rebounds off rotating walls gain energy)")
        if self._dirty:
            self._pack()
        rmin, rmax = self._r_min_max()
        if not math.isfinite(rmin):
            raise MsmillInputError("particles", 0, "at least one particle or source before run()")
        if self._skin is None:
            self._skin = 0.5 * rmin
        self._check_periodic_spans(rmax + self._skin)
        thin = min([g["thickness"] for g in self._geoms if g["thickness"] > 0] + [np.inf])
        lmin = min(rmin, thin)
        vcheck = max(vrel, self._wall_speed_max())
        if dt_s is None:
            dt = safety * self.contact_time_s(vrel)
            dt = min(dt, travel_fraction * lmin / vcheck)
        else:
            dt = _pos_number("dt_s", dt_s)
            self._warn_step(dt, vrel, vcheck, travel_fraction, lmin)
        self._dt = dt
        if not hasattr(self, "_rmax_cells"):
            self._rmax_cells = 0.0
        if rmax > self._rmax_cells:
            self._rmax_cells = rmax
            self._cells(rmax)
        return dt, lmin

    def _warn_step(self, dt: float, vrel: float, vcheck: float, travel_fraction: float, lmin: float) -> None:
        """Warn when a given step is too long for the contact time or lets a body tunnel."""
        tc = self.contact_time_s(vrel)
        if dt > MAX_SAFETY * tc:
            warnings.warn(
                f"dt_s = {dt:.3g} s is {dt / tc:.2g} of the Hertz contact time at "
                f"{vrel:.3g} m/s; above {MAX_SAFETY} the damped contact is integrated "
                "inaccurately (rebounds off rotating walls gain energy)", DemRuntimeWarning,
                stacklevel=4)
        if vcheck * dt > travel_fraction * lmin:
            warnings.warn(
                f"dt_s = {dt:.3g} s lets a body at {vcheck:.3g} m/s travel "
                f"{vcheck * dt:.3g} m per step, more than {travel_fraction} of the smallest "
                f"radius/plate ({lmin:.3g} m): risk of tunnelling", DemRuntimeWarning,
                stacklevel=4)

    def _advance(self, dt: float, limit: int, diag: np.ndarray) -> tuple[int, int]:
        """Up to ``limit`` steps in the compiled loop (threaded or serial, as tuned); ``(steps, reason)``."""
        diag[:] = 0.0
        use_par = self._choose_parallel()
        self._last_par = use_par  # the next rebuild follows the step kernels' choice
        if self._on_device:
            return self._advance_on_device(dt, limit, diag)
        p = self._p
        if self._step_fn is None:
            self._step_fn = stepper(self._backend)
        tic = _time.perf_counter()
        k, reason = self._step_fn(
            self._time, dt, limit, self._skin, self._disp, p["pos"], p["vel"], p["omg"], p["rad"],
            p["mass"], p["invm"], p["invi"], p["mat"], p["pid"], p["frc"], p["trq"], self._kind,
            *self._work, p["flag"], p["flag_t"], self._nb[0], self._nb[1], self._nb[2],
            self._nb[3], self._nb[4], self._stamp + 1, self._pair[0], self._pair[3],
            self._pair[1], self._pair[2],
            self._box_len, self._gc[0], self._gc[1], self._gref, self._gcur, self._grot,
            self._gkind, self._gmat, self._ptab, self._gravity, self._lo, self._hi,
            self._periodic, self._sinkbox, p["h_pid"], p["h_st"], p["h_ev"], p["h_pk"],
            p["h_ds"], p["h_n"], p["h_tch"], p["g_gid"], p["g_st"], p["g_ev"],
            p["g_pk"], p["g_ds"], p["g_n"], p["g_tch"], self._rec.evf, self._rec.evi,
            self._rec.evn, diag, use_par)
        self._stepped(use_par, _time.perf_counter() - tic, k)
        return k, reason

    def _stepped(self, use_par: bool, elapsed: float, k: int) -> None:
        if k > 0:
            self._frc_stale = True  # see _settle_forces
        self.stats["loop_time_s"] += elapsed
        self._tune(use_par, elapsed, k)

    def _advance_on_device(self, dt: float, limit: int, diag: np.ndarray) -> tuple[int, int]:
        """Up to ``limit`` steps on the Warp device, the state staying there; ``(steps, reason)``."""
        tic = _time.perf_counter()
        k, reason = self._device().advance(self, dt, limit, diag)
        self._stepped(False, _time.perf_counter() - tic, k)
        return k, reason

    def _check_periodic_spans(self, pad: float) -> None:
        """Warn about primitives taken as continuous along a periodic axis that end too close to it."""
        for a in np.nonzero(self._periodic)[0]:
            lo_g, hi_g = self._gaabb[:, a], self._gaabb[:, 3 + a]
            short = ((self._gspan[:, a] != 0) & np.isfinite(lo_g)
                     & ((lo_g > self._lo[a] - pad) | (hi_g < self._hi[a] + pad)))
            for k in np.nonzero(short)[0]:
                self._warn_once(
                    f"span{k}{a}",
                    f"geometry {k} ({self._geoms[k]['tag']}) is at least one period long along "
                    f"periodic axis {a}, so it is taken as continuous along it, but it ends less "
                    f"than r_max + skin = {pad:.3g} m beyond the periodic box: particles at the "
                    "boundary meet its end; extend it by that much or make it shorter than the period")

    def _flush_events(self) -> None:
        self._rec.flush([(self._p["h_ev"], self._p["h_n"]), (self._p["g_ev"], self._p["g_n"])])

    def _check_diag(self, diag, dt, max_over, travel_fraction, lmin, wall_v) -> None:
        top = diag.max(axis=0)  # two reductions per call instead of five (called per kernel call)
        total = diag.sum(axis=0)
        over = float(top[K.D_OVER])
        if over > max_over:
            self._warn_once("overlap", f"peak overlap {over:.3g} of the smaller radius exceeds "
                            f"{max_over} at t = {self._time:.6g} s: the material is too soft "
                            "for the impact speed or dt_s is too large")
        vmax = math.sqrt(float(top[K.D_SPEED2]))
        if (vmax + wall_v) * dt > travel_fraction * lmin * 1.0001:
            self._warn_once("travel", f"particle speed {vmax:.3g} m/s (+ wall {wall_v:.3g} m/s) "
                            f"moves {(vmax + wall_v) * dt:.3g} m per step, more than "
                            f"{travel_fraction} of the smallest radius/plate: raise "
                            "max_relative_speed_m_s or lower dt_s")
        if total[K.D_HOVF] > 0:
            self._warn_once("slots", "contact-history slots overflowed; raise "
                            "max_contacts_per_particle / max_geometry_contacts")
        if total[K.D_EVOVF] > 0:
            self._rec.lost += int(total[K.D_EVOVF])
            self._warn_once("events", "event buffer overflowed; some events were not recorded")

    def _record_ts(self) -> None:
        p = self._host_view()
        ke = float(0.5 * np.sum(p["mass"] * np.sum(p["vel"] ** 2, axis=1))
                   + 0.5 * np.sum(np.sum(p["omg"] ** 2, axis=1) / p["invi"]))
        self._ts.append((self._time, self.n_particles, float(p["mass"].sum()), ke,
                         self._mass_out, self._n_lost, sum(s["inserted_kg"] for s in self._sources)))

    # ------------------------------------------------------------------ outputs
    @property
    def time_s(self) -> float:
        """Current simulated time (s)."""
        return self._time

    @property
    def dt_s(self) -> float | None:
        """Time step of the last run (s)."""
        return self._dt

    @property
    def neighbor_skin_m(self) -> float | None:
        """Verlet skin of the neighbour lists (m); None until the first run picks the default.

        Setting it between runs re-sizes the cells and rebuilds the lists at the next step (the
        trajectory stays a valid one; it is not bitwise the one of the old skin: candidate order
        changes the summation order of contact forces).
        """
        return self._skin

    @neighbor_skin_m.setter
    def neighbor_skin_m(self, skin_m: float) -> None:
        self._skin = _pos_number("neighbor_skin_m", skin_m)
        if getattr(self, "_rmax_cells", 0.0) > 0.0:
            self._cells(self._rmax_cells)
        self._need_rebuild = True

    @property
    def backend(self) -> str:
        """The step kernels in use (:data:`msmill.dem.backend.BACKENDS`)."""
        return self._backend

    @property
    def n_particles(self) -> int:
        """Number of particles in the domain."""
        return int(self._pd["pid"].shape[0])

    def particle_arrays(self) -> dict[str, np.ndarray]:
        """Copies of per-particle arrays: ``pid``, ``pos`` (m), ``vel`` (m/s), ``omg`` (rad/s),
        ``rad`` (m), ``mass`` (kg), ``frc`` (N) and ``trq`` (N m) of the last force pass."""
        self._settle_forces()
        p = self._host_view()
        return {k: p[k].copy() for k in ("pid", "pos", "vel", "omg", "rad", "mass", "frc",
                                               "trq")}

    def kinetic_energy_j(self) -> float:
        """Translational plus rotational kinetic energy (J)."""
        p = self._host_view()
        return float(0.5 * np.sum(p["mass"] * np.sum(p["vel"] ** 2, axis=1))
                     + 0.5 * np.sum(np.sum(p["omg"] ** 2, axis=1) / p["invi"]))

    def momentum_kg_m_s(self) -> np.ndarray:
        """Total linear momentum (kg m/s)."""
        p = self._host_view()
        return np.sum(p["mass"][:, None] * p["vel"], axis=0)

    def contact_energy_j(self) -> float:
        """Elastic energy stored in the normal contacts now (J)."""
        if self._need_rebuild or self._dirty:
            if self._dirty:
                self._pack()
            if not hasattr(self, "_rmax_cells") or self._skin is None:
                return 0.0
            self._rebuild()
        p = self._host_view(lists=True)
        return float(K.contact_potential_energy(
            p["pos"], p["rad"], p["pid"], p["mat"], self._nb[0], self._nb[1], self._nb[2],
            self._box_len, self._ptab, self._gc[0], self._gc[1], self._gcur, self._gkind,
            self._gmat))

    def events(self, since_s: float | None = None) -> pd.DataFrame:
        """One row per contact, recorded at onset (see docs/interfaces.md for the columns).

        ``since_s`` (s): only the contacts opened at or after it (None: all).
        """
        self._host_view()
        df = self._rec.frame(since_s)
        geo = self.geometry()
        tag = np.full(len(df), "", dtype=object)
        grp = np.full(len(df), -1, dtype=np.int64)
        m = df["partner_kind"].to_numpy() == 1
        if m.any() and len(geo):
            gid = df["partner_id"].to_numpy()[m]
            tag[m] = geo["tag"].to_numpy()[gid]
            grp[m] = geo["group"].to_numpy()[gid]
        df["partner_tag"] = tag
        df["partner_group"] = grp
        return df

    def removed(self) -> pd.DataFrame:
        """Deleted particles: ``particle_id, time_s, radius_m, mass_kg, tag`` (sink tag or 'lost')."""
        cols = ["particle_id", "time_s", "radius_m", "mass_kg", "tag"]
        if not self._removed:
            return pd.DataFrame({c: [] for c in cols})
        return pd.DataFrame({c: np.concatenate([r[c] for r in self._removed]) for c in cols})

    def timeseries(self) -> pd.DataFrame:
        """``time_s, n_particles, mass_kg, kinetic_energy_j, mass_out_kg, n_lost, mass_in_kg``.

        ``mass_out_kg`` is the cumulative mass removed by sinks, ``mass_in_kg``
        the cumulative mass the sources placed (kg).
        """
        return pd.DataFrame(self._ts, columns=["time_s", "n_particles", "mass_kg",
                                               "kinetic_energy_j", "mass_out_kg", "n_lost", "mass_in_kg"])

    def snapshot(self) -> pd.DataFrame:
        """Particles now: id, position (m), velocity (m/s), angular velocity (rad/s), radius (m)."""
        p = self._host_view()
        return pd.DataFrame({
            "particle_id": p["pid"].copy(), "x_m": p["pos"][:, 0].copy(),
            "y_m": p["pos"][:, 1].copy(), "z_m": p["pos"][:, 2].copy(),
            "vx_m_s": p["vel"][:, 0].copy(), "vy_m_s": p["vel"][:, 1].copy(),
            "vz_m_s": p["vel"][:, 2].copy(), "wx_rad_s": p["omg"][:, 0].copy(),
            "wy_rad_s": p["omg"][:, 1].copy(), "wz_rad_s": p["omg"][:, 2].copy(),
            "radius_m": p["rad"].copy(),
            "material": np.array([m["name"] for m in self._materials], dtype=object)[p["mat"]]
            if self._materials else np.zeros(0)})

    def snapshots(self) -> list[tuple[float, pd.DataFrame]]:
        """Snapshots taken during runs (``snapshot_every_s``): list of (time_s, DataFrame)."""
        return list(self._snaps)

    def geometry(self) -> pd.DataFrame:
        """``geom_id, kind, tag, group, material, rotating, omega_rad_s``."""
        g = self._geoms
        return pd.DataFrame({
            "geom_id": np.arange(len(g), dtype=np.int64),
            "kind": [KIND_NAMES[x["kind"]] for x in g],
            "tag": [x["tag"] for x in g],
            "group": np.array([x["group"] for x in g], dtype=np.int64),
            "material": [self._materials[x["mat"]]["name"] for x in g],
            "rotating": [bool(x["rot"][7] > 0) for x in g],
            "omega_rad_s": [float(x["rot"][6]) for x in g]})

    def write_events_parquet(self, path: str | Path) -> Path:
        """Write :meth:`events` as Parquet."""
        return write_parquet(self.events(), path)

    def write_vtu(self, path: str | Path) -> Path:
        """Write the particles now as a VTK ``.vtu`` file for ParaView."""
        p = self._host_view()
        return write_vtu(path, p["pos"], {"particle_id": p["pid"], "radius_m": p["rad"],
                                          "velocity_m_s": p["vel"],
                                          "angular_velocity_rad_s": p["omg"],
                                          "material": p["mat"]})
