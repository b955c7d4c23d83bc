"""The surrogate as a stage-parameter provider for the mill model.

:class:`SurrogateProvider` implements :class:`msmill.providers_base.StageParameterProvider`:
it predicts every stage's statistics at the requested operating point (each
stage at its own speed; see :mod:`msmill.surrogate.stage_model`), so its
velocities are already those at the requested speeds
(``velocities_at_requested_speeds = True``: the ``speed_scaled`` impact model
does not rescale them). :meth:`SurrogateProvider.sample_stage_parameters`
draws stage parameters from the GP posterior, which the mill model turns into
uncertainty bands on the product.

Warnings (:class:`msmill.errors.OutOfDomainWarning`, saying by how much):
sizes, feed rate, gate angle or a stage's (equivalent) speed outside what the
surrogate was trained on, and operating points outside the design space;
(:class:`msmill.errors.ThinDataWarning`) size classes inside the trained box
that lie far from every training run (:meth:`StageSurrogate.data_support`),
naming the nearest run.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from msmill.errors import OutOfDomainWarning, SummaryNote, ThinDataWarning
from msmill.providers_base import CountArrays, MixtureArrays, StageParameters
from msmill.surrogate.space import INPUTS
from msmill.surrogate.stage_model import StageSurrogate
from msmill.surrogate.targets import count_arrays_from_summary, decode_inlet_destinations

_UNITS = {"size_mm": "mm", "feed_tph": "t/h", "speed_rpm": "rpm", "gate_deg": "deg"}
#: Sets of target rows decoded together by ``SurrogateProvider._params``.
DECODE_CHUNK_SETS = 64
#: Rows per call of :func:`count_arrays_from_summary` (its (rows, 400) work arrays stay in cache:
#: ~15x faster than one call over a whole band's 64 x 5 x N rows).
COUNT_CHUNK_ROWS = 256


def _count_arrays(mean: np.ndarray, var_ratio: np.ndarray, p_zero: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`count_arrays_from_summary` over arrays of any shape, in chunks of :data:`COUNT_CHUNK_ROWS`."""
    flat = [np.asarray(a, dtype=float).ravel() for a in (mean, var_ratio, p_zero)]
    parts = [count_arrays_from_summary(*(a[i:i + COUNT_CHUNK_ROWS] for a in flat))
             for i in range(0, flat[0].size, COUNT_CHUNK_ROWS)]
    shape = (*np.shape(mean), -1)
    return tuple(np.concatenate([p[k] for p in parts]).reshape(shape) for k in (0, 1))


class SurrogateProvider:
    """Stage parameters predicted by a trained :class:`StageSurrogate`.

    Parameters
    ----------
    surrogate : StageSurrogate
        A fitted surrogate.
    source : str
        Description used in warnings and result notes.
    """

    velocities_at_requested_speeds = True

    def __init__(self, surrogate: StageSurrogate, source: str = "GP surrogate") -> None:
        self.surrogate = surrogate
        #: slice-to-full-mill correction (:class:`msmill.surrogate.fidelity.SliceToFullBias`) or None
        self.correction = getattr(surrogate, "slice_to_full_", None)
        if self.correction is not None and self.correction.n_pairs:
            source = f"{source} (slice-to-full corrected, {self.correction.n_pairs} pairs)"
        self.source = source

    @classmethod
    def from_file(cls, path: str | Path) -> SurrogateProvider:
        """Load a surrogate JSON written by :func:`msmill.surrogate.persist.save`."""
        from msmill.surrogate.persist import load

        return cls(load(path), source=Path(path).name)

    @property
    def trained_machine(self) -> dict[str, str] | None:
        """The machine of the training runs (``name``, ``rotation_sense``, ``geometry_hash``: see
        :meth:`msmill.machine.Machine.geometry_hash`) as the build recorded it; None if it did not."""
        m = getattr(self.surrogate, "provenance_", {}).get("machine")
        return dict(m) if isinstance(m, dict) and "geometry_hash" in m else None

    @property
    def covered_sizes_mm(self) -> tuple[float, float]:
        """Smallest and largest rock size (mm) of the training runs."""
        lo, hi = self.surrogate.domain_[0]
        return float(lo), float(hi)

    @property
    def n_stages(self) -> int:
        """Number of stages of the surrogate."""
        return self.surrogate.n_stages

    def _inputs(self, sizes_mm, stage_speeds_rpm, feed_tph, gate_deg) -> np.ndarray:
        m = self.surrogate
        d = m.domain_
        if stage_speeds_rpm is None:
            stage_speeds_rpm = list(np.median(d[2]) * m.speed_factors)
        feed = float(np.mean(d[1]) if feed_tph is None else feed_tph)
        gate = float(np.mean(d[3]) if gate_deg is None else gate_deg)
        X = m.stage_inputs(sizes_mm, stage_speeds_rpm, feed, gate)
        self._warn_domain(X)
        return X

    def _warn_domain(self, X: np.ndarray) -> None:
        m = self.surrogate
        ex = m.domain_excess(X)  # (S, N, 4)
        msgs = []
        sizes = X[0, :, 0]
        out = ex[0, :, 0] > 1e-9
        if out.any():
            lo, hi = m.domain_[0]
            parts = []
            if sizes.min() < lo:
                parts.append(f"down to {sizes.min():.3g} mm, {lo / sizes.min():.3g}x below the smallest")
            if sizes.max() > hi:
                parts.append(f"up to {sizes.max():.3g} mm, {sizes.max() / hi:.3g}x above the largest")
            # every feed has fines below the trained sizes: a summary note, not a warning
            warnings.warn(f"{self.source}: extrapolating: {int(out.sum())} of {sizes.size} size classes outside "
                          f"the trained {lo:g}-{hi:g} mm ({'; '.join(parts)})", SummaryNote, stacklevel=3)
        for k in (1, 3):
            if ex[0, 0, k] > 1e-9:
                lo, hi = m.domain_[k]
                msgs.append(f"{INPUTS[k]} {X[0, 0, k]:g} {_UNITS[INPUTS[k]]} is {ex[0, 0, k]:.3g} "
                            f"{_UNITS[INPUTS[k]]} outside the trained {lo:g}-{hi:g}")
        lo, hi = m.domain_[2]
        for s in np.flatnonzero(ex[:, 0, 2] > 1e-9):
            speed = X[s, 0, 2] * m.speed_factors[s]
            msgs.append(f"stage {s + 1} speed {speed:g} rpm (equivalent upper-stage speed {X[s, 0, 2]:g} rpm) "
                        f"is {ex[s, 0, 2] * m.speed_factors[s]:.3g} rpm outside the "
                        f"{lo * m.speed_factors[s]:g}-{hi * m.speed_factors[s]:g} rpm it was trained on")
        space = m.design_space.bounds
        for k in (1, 2, 3):
            v = X[..., k]
            beyond = float(max(space[k, 0] - v.min(), v.max() - space[k, 1], 0.0))
            if beyond > 0:
                msgs.append(f"{INPUTS[k]} lies {beyond:.3g} {_UNITS[INPUTS[k]]} outside the design space "
                            f"{space[k, 0]:g}-{space[k, 1]:g}")
        if msgs:
            warnings.warn(f"{self.source}: extrapolating: " + "; ".join(msgs), OutOfDomainWarning, stacklevel=3)

    def _thin(self, X: np.ndarray) -> np.ndarray:
        """Size classes inside the trained sizes whose point lies far from every training run (warned once)."""
        m = self.surrogate
        inside = m.domain_excess(X)[0, :, 0] <= 1e-9
        thin = np.zeros(X.shape[1], dtype=bool)
        if not inside.any():  # every class is extrapolated in size (warned as such): none is "thin"
            return thin
        sup = m.data_support(X[0, inside])  # the posterior spread only where it can flag (the classes inside)
        thin[inside] = sup.thin
        if thin.any():
            j = int(np.argmax(np.where(sup.thin, sup.spread_ratio, -np.inf)))  # among the inside classes
            k = int(np.flatnonzero(inside)[j])
            r = m.training_.X[sup.nearest_run[j]]
            sizes = X[0, thin, 0]
            warnings.warn(
                f"{self.source}: thin data: {int(thin.sum())} of {int(inside.sum())} size classes inside the trained "
                f"sizes ({sizes.min():.3g}-{sizes.max():.3g} mm) lie far from every training run (posterior "
                f"spread {sup.spread_ratio[j]:.3g} of the prior against at most {sup.threshold:.3g} at 90 % of "
                f"the runs); nearest run to {X[0, k, 0]:.3g} mm: {r[0]:.3g} mm, {r[1]:.3g} t/h, {r[2]:.0f} rpm, "
                f"{r[3]:.0f} deg ({sup.nearest_distance[j]:.2f} of the unit design cube away)",
                ThinDataWarning, stacklevel=3)
        return thin

    def _params(self, Ys: np.ndarray, sizes_mm: np.ndarray, X: np.ndarray,
                thin: np.ndarray | None = None) -> list[StageParameters]:
        """Stage parameters of target rows ``Ys`` (n, S, N, T): the sets decoded in batches of up to 64."""
        if len(Ys) > DECODE_CHUNK_SETS:  # bounded memory: the decode copies the rows
            return [p for i in range(0, len(Ys), DECODE_CHUNK_SETS)
                    for p in self._params(Ys[i:i + DECODE_CHUNK_SETS], sizes_mm, X, thin)]
        m = self.surrogate
        n, S, N, T = Ys.shape
        flat = np.swapaxes(Ys, 0, 1).reshape(S, n * N, T)  # every set's rows side by side
        preds = m.decode(flat)
        per = lambda a: np.swapaxes(np.reshape(a, (S, n, N, *np.shape(a)[2:])), 0, 1)  # noqa: E731  (n, S, N, ...)
        get = lambda f: per(np.stack([f(p) for p in preds]))  # noqa: E731
        mixes = {k: [get(lambda p, k=k, i=i: getattr(p, k)[i]) for i in range(3)]
                 for k in ("primary_velocity", "secondary_velocity")}
        streams, hit, lam = get(lambda p: p.streams), get(lambda p: p.hit_probability), get(lambda p: p.secondary_lambda)
        counts = None
        if preds[0].count_var_ratio is not None:  # the runs carried count distributions (schema v2)
            counts = [per(a) for a in _count_arrays(
                np.stack([p.secondary_lambda for p in preds]), np.stack([p.count_var_ratio for p in preds]),
                np.stack([p.count_p_zero for p in preds]))]
        tr = None
        if preds[0].destinations is not None:  # the dem_matrix transport: inlet zone row, then every stage's
            inlet = decode_inlet_destinations(flat[0], m.training_.layout).reshape(n, 1, N, -1)  # stage 1's points
            tr = np.concatenate([inlet, get(lambda p: p.destinations)], axis=1)  # (n, S + 1, N, S + 2)
        rw = rs = None
        if preds[0].region_weights is not None:
            rw, rs = get(lambda p: p.region_weights), get(lambda p: p.region_streams)
        sizes = np.asarray(sizes_mm, dtype=float)
        extrapolated = m.domain_excess(X)[0, :, 0] > 1e-9  # sizes outside the trained ones
        lag = np.exp(Ys[:, 0, :, -1])  # each size's matrix was measured at its run's characteristic time
        return [StageParameters(
            sizes_mm=sizes.copy(),
            characteristic_time_s=m.characteristic_time_s(Ys[i]),
            streams=streams[i], hit_probability=hit[i],
            primary_velocity=MixtureArrays(*(a[i] for a in mixes["primary_velocity"])),
            secondary_lambda=lam[i],
            secondary_velocity=MixtureArrays(*(a[i] for a in mixes["secondary_velocity"])),
            design_stage_speeds_rpm=X[:, 0, 2] * m.speed_factors,
            design_feed_tph=float(X[0, 0, 1]), design_gate_deg=float(X[0, 0, 3]),
            region_weights=None if rw is None else rw[i], region_streams=None if rs is None else rs[i],
            source=self.source, velocities_at_requested_speeds=True,
            secondary_count=None if counts is None else CountArrays(counts[0][i], counts[1][i]),
            extrapolated=extrapolated.copy(), thin_data=None if thin is None else thin.copy(),
            transition=None if tr is None else tr[i], transition_lag_s=None if tr is None else lag[i],
        ) for i in range(n)]

    def stage_parameters(self, sizes_mm, stage_speeds_rpm=None, feed_tph=None, gate_deg=None) -> StageParameters:
        """Posterior-mean stage parameters at ``sizes_mm`` (mm) and the operating point (slice-to-full corrected)."""
        X = self._inputs(sizes_mm, stage_speeds_rpm, feed_tph, gate_deg)
        Y = self.surrogate.predict_targets(X)
        if self.correction is not None:
            Y = self.correction.apply(Y)
        return self._params(Y[None], sizes_mm, X, self._thin(X))[0]

    def sample_stage_parameters(self, sizes_mm, n_samples: int, stage_speeds_rpm=None, feed_tph=None,
                                gate_deg=None, seed: int | None = 0) -> list[StageParameters]:
        """``n_samples`` draws of the stage parameters from the GP posterior (jointly over sizes)."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", OutOfDomainWarning)  # already said by stage_parameters
            warnings.simplefilter("ignore", SummaryNote)
            X = self._inputs(sizes_mm, stage_speeds_rpm, feed_tph, gate_deg)
        rng = np.random.default_rng(seed)
        Z = self.surrogate.sample_targets(X, n_samples, rng=rng)
        if self.correction is not None:
            Z = self.correction.sample(Z, rng)
        return self._params(Z, sizes_mm, X)

    def __repr__(self) -> str:
        return f"SurrogateProvider({self.source}, {self.surrogate!r})"
