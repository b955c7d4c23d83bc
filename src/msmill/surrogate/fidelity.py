"""Slice-to-full-mill correction of the surrogate's targets, with its own uncertainty.

The campaign trains on periodic-slice DEM runs; a slice matches the full mill's
streams within 0.02 but gives 19-36 % fewer secondary impacts per primary
impact (``docs/mill-dem.md``, "Full-mill run"). :class:`SliceToFullBias` is a
per-target offset in the surrogate's target space (``msmill.surrogate.targets``),
estimated from pairs of slice and full-mill runs at the same design point::

    y_full = y_slice + b + e,   e ~ N(0, var_b)

so the correction is multiplicative where the target is a logarithm (the
secondary-impact count ``ln(lambda)``, velocity-quantile increments, the time
step), an odds ratio for the hit probability (logit) and a ratio of stream
ratios for the streams (additive log-ratios).

Estimate over ``n`` pairs with differences ``d_i = y_full,i - y_slice,i`` and
sampling variances ``s_i`` (the two runs' delta-method variances added):

* ``b = mean(d_i)``;
* between-point scatter ``tau^2 = max(var(d_i) - mean(s_i), 0)`` for ``n >= 2``;
  with one pair it cannot be estimated and ``tau^2 = max(d_1^2 - s_1, 0)`` (the
  part of the difference the sampling noise does not explain is taken to be as
  uncertain as it is large: conservative);
* ``var_b = mean(s_i) / n + tau^2 (1 + 1/n)`` — the uncertainty of the mean plus
  the scatter of the bias at a new design point.

:class:`msmill.surrogate.provider.SurrogateProvider` adds ``b`` to the
posterior mean and, in the band samples, one draw of ``N(b, var_b)`` per
sample and target (the same at every size: the bias is systematic), so the
correction's uncertainty widens the band.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from msmill.errors import MsmillInputError
from msmill.stageparams import RunStatistics
from msmill.surrogate.targets import TargetLayout, encode_run

__all__ = ["SliceToFullBias", "match_pairs"]

#: relative tolerance on the design inputs for a slice and a full run to form a pair
PAIR_RTOL = 1e-3


def _inputs(run: RunStatistics) -> np.ndarray:
    d = run.design
    return np.array([*d.inputs(), *d.stage_speeds_rpm], dtype=float)


def match_pairs(slices: list[RunStatistics], fulls: list[RunStatistics]) -> list[tuple[RunStatistics, RunStatistics]]:
    """Pair every full-mill run with the slice run at the same design point (unpaired ones are dropped)."""
    out = []
    for f in fulls:
        xf = _inputs(f)
        for s in slices:
            xs = _inputs(s)
            if xs.shape == xf.shape and np.allclose(xs, xf, rtol=PAIR_RTOL, atol=1e-9):
                out.append((s, f))
                break
    return out


@dataclass(frozen=True)
class SliceToFullBias:
    """Per-target offset ``full - slice`` in target space and its variance.

    Attributes
    ----------
    offset : ndarray (T,)
        ``b`` per target of the layout.
    var : ndarray (T,)
        ``var_b`` per target (predictive: includes the scatter at a new point).
    n_pairs : int
        Number of slice/full pairs behind the estimate.
    pairs : tuple of str
        Design points of the pairs (``size-feed-speed-gate``).
    """

    offset: np.ndarray
    var: np.ndarray
    n_pairs: int
    pairs: tuple[str, ...] = ()
    groups: tuple[str, ...] | None = None

    @classmethod
    def fit(cls, layout: TargetLayout, pairs: list[tuple[RunStatistics, RunStatistics]],
            groups: tuple[str, ...] | None = None) -> SliceToFullBias:
        """Estimate from ``(slice, full)`` run pairs at the same design points (see the module docstring).

        ``groups`` limits the correction to these per-stage target groups
        (``streams``, ``hit``, ``primary_velocity``, ``secondary_velocity``,
        ``count``, ...; the run-level time is never corrected then); the other
        targets get offset and variance 0. ``None``: every target.
        """
        if not pairs:
            raise MsmillInputError("pairs", 0, "at least one (slice, full) pair of runs at the same design point")
        enc = [(encode_run(s, layout), encode_run(f, layout)) for s, f in pairs]
        d = np.array([yf - ys for (ys, _), (yf, _) in enc])
        s = np.array([vs + vf for (_, vs), (_, vf) in enc])
        n = len(pairs)
        b = d.mean(axis=0)
        spread = d.var(axis=0, ddof=1) if n >= 2 else d[0] ** 2
        tau2 = np.maximum(spread - s.mean(axis=0), 0.0)
        var = s.mean(axis=0) / n + tau2 * (1.0 + 1.0 / n)
        if groups is not None:
            known = {g for g, _ in layout.groups()}
            if not set(groups) <= known:
                raise MsmillInputError("groups", ", ".join(sorted(set(groups) - known)), ", ".join(sorted(known)))
            keep = np.zeros(layout.n_targets, dtype=bool)
            for st in range(1, layout.n_stages + 1):
                for g in groups:
                    keep[layout.slices(st)[g]] = True
            b, var = np.where(keep, b, 0.0), np.where(keep, var, 0.0)
        labels = tuple(f"{p.design.size_mm:g}mm-{p.design.feed_tph:g}tph-{p.design.speed_rpm:g}rpm-"
                       f"{p.design.gate_deg:g}deg" for p, _ in pairs)
        return cls(b, var, n, labels, None if groups is None else tuple(groups))

    @classmethod
    def none(cls, layout: TargetLayout) -> SliceToFullBias:
        """No correction (zero offset and variance)."""
        z = np.zeros(layout.n_targets)
        return cls(z, z.copy(), 0)

    def apply(self, Y: np.ndarray) -> np.ndarray:
        """Corrected target rows: ``Y + b`` (broadcast over the last axis)."""
        return np.asarray(Y) + self.offset

    def sample(self, Z: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Corrected posterior samples ``(n, S, N, T)``: one bias draw per sample and target, shared by all sizes."""
        n = Z.shape[0]
        draw = self.offset + rng.standard_normal((n, self.offset.size)) * np.sqrt(self.var)
        return Z + draw[:, None, None, :]

    def lambda_factors(self, layout: TargetLayout) -> list[dict[str, float]]:
        """Per stage: full/slice factor on ``lambda`` (``exp(b)``) and its 1-sigma relative uncertainty."""
        out = []
        for s in range(1, layout.n_stages + 1):
            i = layout.slices(s)["count"].start
            out.append({"stage": s, "lambda_factor": float(np.exp(self.offset[i])),
                        "lambda_factor_sd": float(np.exp(self.offset[i]) * np.sqrt(self.var[i]))})
        return out

    def to_dict(self) -> dict[str, Any]:
        """Plain dict for the surrogate JSON."""
        return {"offset": [float(v) for v in self.offset], "var": [float(v) for v in self.var],
                "n_pairs": self.n_pairs, "pairs": list(self.pairs),
                "groups": None if self.groups is None else list(self.groups),
                "model": "y_full = y_slice + b, b ~ N(offset, var) per target (msmill.surrogate.fidelity)"}

    @classmethod
    def from_dict(cls, d: dict[str, Any], n_targets: int) -> SliceToFullBias:
        """Inverse of :meth:`to_dict`; checks the length against the layout."""
        off, var = np.array(d["offset"], dtype=float), np.array(d["var"], dtype=float)
        if off.shape != (n_targets,) or var.shape != (n_targets,) or (var < 0).any():
            raise MsmillInputError("surrogate.slice_to_full", f"{off.size} offsets",
                                   f"{n_targets} offsets and non-negative variances")
        g = d.get("groups")
        return cls(off, var, int(d.get("n_pairs", 0)), tuple(d.get("pairs", ())), None if g is None else tuple(g))
