"""Capacity of the mill as a predicted quantity: the largest feed rate it passes without choking.

Data are DEM runs with an outcome (:mod:`msmill.steadystate`): a **steady**
run at ``(size, feed, speeds, gate)`` passed its feed; a **choked** run did not
and passed only its measured product rate ``throughput_tph``. By conservation
of mass a mill that passes ``T`` when fed more is taken to be steady when fed
``T`` (``throughput_as_steady``, on by default): every choked run adds a
steady pseudo-point at its throughput. Not-steady runs (the time limit was
hit while still filling) carry no capacity information and are left out.

A Gaussian-process classifier (scikit-learn, anisotropic RBF kernel on
``log size``, ``feed``, ``speed``, ``gate``, each scaled to about unit range)
gives the probability that the mill is steady at a point; the capacity at a
given size, speed and gate is the smallest feed rate at which that
probability falls below one half, searched on a fine grid of feed rates.
``inf`` means no choke was predicted up to the top of the grid.

The model is a library object: :func:`warn_if_above_capacity` is the hook
``msmill predict`` and the practitioner tools call; the surrogate can use
:meth:`CapacityModel.probability_steady` as a constraint.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from msmill.errors import MsmillInputError
from msmill.stageparams import RunStatistics

__all__ = ["AboveCapacityWarning", "CapacityModel", "EnvelopeData", "EnvelopePoint", "warn_if_above_capacity"]

_SCALE = np.array([1.0, 60.0, 1900.0, 80.0])  # log(size/mm), t/h, rpm, deg: about unit range over the design space


class AboveCapacityWarning(UserWarning):
    """The requested feed rate is above the mill's predicted capacity."""


@dataclass(frozen=True)
class EnvelopePoint:
    """One DEM run's operating point and outcome (feed and throughput full-mill t/h)."""

    size_mm: float
    feed_tph: float
    speed_rpm: float
    gate_deg: float
    outcome: str
    throughput_tph: float | None = None

    @classmethod
    def from_statistics(cls, st: RunStatistics) -> EnvelopePoint:
        """The point of a run's statistics (``outcome`` None counts as steady)."""
        d = st.design
        return cls(size_mm=d.size_mm, feed_tph=d.feed_tph, speed_rpm=d.speed_rpm, gate_deg=d.gate_deg,
                   outcome=st.outcome or "steady", throughput_tph=st.throughput_tph)


@dataclass
class EnvelopeData:
    """Envelope points with provenance; JSON ``{"points": [...], "provenance": {...}}``."""

    points: list[EnvelopePoint]
    provenance: dict[str, Any] = field(default_factory=dict)

    def to_json(self, path: str | Path) -> None:
        """Write the points and provenance as JSON."""
        doc = {"points": [asdict(p) for p in self.points], "provenance": self.provenance}
        Path(path).write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")

    @classmethod
    def from_json(cls, path: str | Path) -> EnvelopeData:
        """Read a file written by :meth:`to_json`; errors are one line."""
        p = Path(path)
        try:
            doc = json.loads(p.read_text(encoding="utf-8"))
            pts = [EnvelopePoint(**x) for x in doc["points"]]
        except (OSError, json.JSONDecodeError, KeyError, TypeError) as exc:
            raise MsmillInputError(str(p), type(exc).__name__, "an envelope JSON file ({'points': [...]})") from None
        return cls(pts, doc.get("provenance", {}))


def _features(size_mm: Any, feed_tph: Any, speed_rpm: Any, gate_deg: Any) -> np.ndarray:
    cols = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (size_mm, feed_tph, speed_rpm, gate_deg)))
    x = np.column_stack([c.ravel() for c in cols])
    x[:, 0] = np.log(x[:, 0])
    return x / _SCALE


@dataclass
class CapacityModel:
    """Gaussian-process classifier of steady vs choked (module docstring)."""

    classifier: Any
    n_steady: int
    n_choked: int

    @classmethod
    def fit(cls, points: list[EnvelopePoint], throughput_as_steady: bool = True, seed: int = 0) -> CapacityModel:
        """Fit to steady and choked points (not-steady points are ignored).

        Raises
        ------
        MsmillInputError
            If the points hold no steady or no choked run (nothing to separate).
        """
        from sklearn.exceptions import ConvergenceWarning
        from sklearn.gaussian_process import GaussianProcessClassifier
        from sklearn.gaussian_process.kernels import RBF, ConstantKernel

        rows, labels = [], []
        for p in points:
            if p.outcome == "steady":
                rows.append((p.size_mm, p.feed_tph, p.speed_rpm, p.gate_deg))
                labels.append(1)
            elif p.outcome == "choked":
                rows.append((p.size_mm, p.feed_tph, p.speed_rpm, p.gate_deg))
                labels.append(0)
                if throughput_as_steady and p.throughput_tph:
                    rows.append((p.size_mm, p.throughput_tph, p.speed_rpm, p.gate_deg))
                    labels.append(1)
        y = np.array(labels)
        if y.size == 0 or y.min() == y.max():
            raise MsmillInputError("envelope points", f"{int(y.sum())} steady, {int((y == 0).sum())} choked",
                                   "at least one steady and one choked run")
        x = _features(*np.array(rows).T)
        kernel = ConstantKernel(1.0, (1e-2, 1e5)) * RBF(np.ones(4), (0.05, 20.0))
        with warnings.catch_warnings():  # hyper-parameters at a bound are fine for a few points
            warnings.simplefilter("ignore", ConvergenceWarning)
            gpc = GaussianProcessClassifier(kernel=kernel, random_state=seed, n_restarts_optimizer=0).fit(x, y)
        return cls(gpc, int(y.sum()), int((y == 0).sum()))

    def probability_steady(self, size_mm: Any, feed_tph: Any, speed_rpm: Any, gate_deg: Any) -> np.ndarray:
        """Probability that the mill is steady (passes its feed) at the given points (broadcast)."""
        return self.classifier.predict_proba(_features(size_mm, feed_tph, speed_rpm, gate_deg))[:, 1]

    def capacity_tph(self, size_mm: float, speed_rpm: float, gate_deg: float,
                     feed_range_tph: tuple[float, float] = (1.0, 120.0), n_grid: int = 240) -> float:
        """Smallest feed rate (t/h) at which the steady probability falls below 1/2; ``inf`` if none on the grid."""
        f = np.linspace(*feed_range_tph, n_grid)
        p = self.probability_steady(size_mm, f, speed_rpm, gate_deg)
        below = np.flatnonzero(p < 0.5)
        if below.size == 0:
            return float("inf")
        j = int(below[0])
        if j == 0:
            return float(f[0])
        # linear interpolation of the crossing between grid points j - 1 and j
        return float(f[j - 1] + (p[j - 1] - 0.5) / (p[j - 1] - p[j]) * (f[j] - f[j - 1]))


def warn_if_above_capacity(model: CapacityModel | None, size_mm: float, feed_tph: float, speed_rpm: float,
                           gate_deg: float) -> float | None:
    """Warn (:class:`AboveCapacityWarning`) if ``feed_tph`` exceeds the predicted capacity; return the capacity.

    ``model`` None (no envelope data yet) does nothing and returns None.
    """
    if model is None:
        return None
    cap = model.capacity_tph(size_mm, speed_rpm, gate_deg)
    if feed_tph > cap:
        warnings.warn(f"feed {feed_tph:g} t/h is above the predicted capacity {cap:.1f} t/h at {size_mm:g} mm, "
                      f"{speed_rpm:g} rpm, gate {gate_deg:g} deg (by {feed_tph - cap:.1f} t/h): the mill is "
                      "expected to choke", AboveCapacityWarning, stacklevel=2)
    return cap
