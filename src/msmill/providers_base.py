"""Per-stage parameter arrays and the stage-parameter provider protocol (core layer).

The contract between whatever supplies DEM-derived stage statistics (a table of
runs, one run, the Gaussian-process surrogate in :mod:`msmill.surrogate`) and
the mill model (:mod:`msmill.model`) that consumes them. It lives in core so
the surrogate layer can implement a provider without importing the model
layer; :mod:`msmill.model.parameters` and :mod:`msmill.model.providers`
re-export these names.

A provider turns DEM statistics into a :class:`StageParameters`: every field
is an array over ``(stage, size class)`` read at the model's size grid.
Velocity distributions are Gaussian mixtures padded to a common number of
components with zero weights.

Speed contract
--------------
A provider whose velocities are already those at the requested stage speeds
(the surrogate predicts at the operating point) sets the class attribute
``velocities_at_requested_speeds = True`` and returns
:class:`StageParameters` with the same flag; the ``speed_scaled`` impact
model then uses the velocities as given instead of rescaling them by
``speed / design_speed`` a second time. Table and run providers (measured at
one operating point) leave it ``False``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class MixtureArrays:
    """Gaussian mixtures of impact velocity per (stage, size class), in m/s.

    Attributes
    ----------
    weights : ndarray, shape (S, N, K)
        Component weights (sum 1 over the last axis; padding has weight 0).
    means_m_s : ndarray, shape (S, N, K)
        Component means (m/s).
    sigmas_m_s : ndarray, shape (S, N, K)
        Component standard deviations (m/s, > 0).
    """

    weights: np.ndarray
    means_m_s: np.ndarray
    sigmas_m_s: np.ndarray

    def scaled(self, factor: np.ndarray) -> MixtureArrays:
        """Velocities multiplied by ``factor`` (broadcast over (S, N, K))."""
        f = np.asarray(factor, dtype=float)
        return MixtureArrays(self.weights, self.means_m_s * f, self.sigmas_m_s * f)

    def mean_m_s(self) -> np.ndarray:
        """Mean of each mixture (m/s), shape (S, N)."""
        return np.sum(self.weights * self.means_m_s, axis=-1)


@dataclass(frozen=True)
class CountArrays:
    """Secondary-impact count distributions per (stage, size class) as Poisson mixtures.

    ``P(K = k) = sum_c weights[..., c] Poisson(k; means[..., c])`` (see
    :class:`msmill.stageparams.CountDistribution`; a mean of 0 is a point mass at 0).

    Attributes
    ----------
    weights : ndarray, shape (S, N, C)
        Component weights (sum 1 over the last axis; padding has weight 0).
    means : ndarray, shape (S, N, C)
        Component Poisson means (impacts per primary impact, >= 0).
    """

    weights: np.ndarray
    means: np.ndarray

    @classmethod
    def poisson(cls, lam: np.ndarray) -> CountArrays:
        """One Poisson component of mean ``lam`` (S, N) per (stage, size class)."""
        lam = np.asarray(lam, dtype=float)
        return cls(np.ones((*lam.shape, 1)), lam[..., None].copy())

    def mean(self) -> np.ndarray:
        """Mean count per (stage, size class), shape (S, N)."""
        return np.sum(self.weights * self.means, axis=-1)


@dataclass(frozen=True)
class StageParameters:
    """DEM-derived parameters of every stage, read at the model's size classes.

    Attributes
    ----------
    sizes_mm : ndarray, shape (N,)
        Representative rock size of each class (mm).
    characteristic_time_s : float
        Model time step (s).
    streams : ndarray, shape (S, N, 3)
        Bulk ``[kickback, refeed, pass_through]`` per stage and class.
    region_weights : ndarray, shape (S, N, 6) or None
        Solid-fraction weights of the horizontal regions, when the DEM gave them.
    region_streams : ndarray, shape (S, N, 6, 3) or None
        Streams per horizontal region.
    secondary_count : CountArrays or None
        Distribution of the number of secondary impacts (its mean is
        ``secondary_lambda``); None means Poisson of ``secondary_lambda``.
    hit_probability : ndarray, shape (S, N)
        Primary (flinger) hit probability per step.
    primary_velocity : MixtureArrays
        Relative normal velocity of primary impacts (m/s).
    secondary_lambda : ndarray, shape (S, N)
        Mean number of secondary impacts per non-breaking primary impact.
    secondary_velocity : MixtureArrays
        Relative normal velocity of secondary impacts (m/s).
    design_stage_speeds_rpm : ndarray, shape (S,)
        Stage speeds (rpm) at which the statistics were measured.
    design_feed_tph, design_gate_deg : float
        Feed rate (t/h) and gate angle (deg) of the measurements.
    source : str
        Human-readable description of where the parameters came from.
    velocities_at_requested_speeds : bool
        True when the velocities are already those at the operating point the
        parameters were requested for (no further speed scaling; see the
        module docstring).
    transition : ndarray, shape (S+1, N, S+2) or None
        One-step transition of every compartment (0 = inlet zone, 1..S stages)
        to compartments ``0..S`` and ``S+1`` (left through the outlet), when the
        DEM measured it (``destinations``); rows sum to 1.
    extrapolated : ndarray, shape (N,) of bool or None
        Size classes whose parameters were extrapolated outside the sizes measured.
    thin_data : ndarray, shape (N,) of bool or None
        Size classes inside the sizes measured whose parameters rest on thin data: far from every
        training run (a surrogate's posterior spread above what its own runs have, each left out).
    transition_lag_s : ndarray, shape (N,) or None
        Lag (s) at which each class's ``transition`` was measured (the runs'
        characteristic times, interpolated); the transport converts it to the step.
    filling_fill : ndarray, shape (K,) or None
        Mill fills (share of the steady hold-up) at which ``filling_residence_ratio``
        is given; used by the ``dem_matrix_fill`` transport.
    filling_residence_ratio : ndarray, shape (N, K) or (K,), or None
        The transport's mean residence while the mill fills, over its steady one, at
        ``filling_fill``: per size class (N, K), the runs' ``filling_transport``
        interpolated in log size like every other quantity and held at the end
        runs' curves outside the sizes covered; or one curve for all classes (K,).
    """

    sizes_mm: np.ndarray
    characteristic_time_s: float
    streams: np.ndarray
    hit_probability: np.ndarray
    primary_velocity: MixtureArrays
    secondary_lambda: np.ndarray
    secondary_velocity: MixtureArrays
    design_stage_speeds_rpm: np.ndarray
    design_feed_tph: float = float("nan")
    design_gate_deg: float = float("nan")
    region_weights: np.ndarray | None = None
    region_streams: np.ndarray | None = None
    source: str = ""
    velocities_at_requested_speeds: bool = False
    secondary_count: CountArrays | None = None
    transition: np.ndarray | None = None
    extrapolated: np.ndarray | None = None
    thin_data: np.ndarray | None = None
    transition_lag_s: np.ndarray | None = None
    filling_fill: np.ndarray | None = None
    filling_residence_ratio: np.ndarray | None = None

    @property
    def n_stages(self) -> int:
        """Number of stages ``S``."""
        return int(self.streams.shape[0])

    @property
    def n_sizes(self) -> int:
        """Number of size classes ``N``."""
        return int(self.streams.shape[1])


@runtime_checkable
class StageParameterProvider(Protocol):
    """Anything that gives per-stage parameters at the model's size classes.

    Optional extensions the mill model uses when present:
    ``velocities_at_requested_speeds`` (bool class attribute, see the module
    docstring) and ``sample_stage_parameters(sizes_mm, n_samples,
    stage_speeds_rpm, feed_tph, gate_deg, seed)`` returning a list of
    :class:`StageParameters` drawn from the provider's predictive distribution
    (used for uncertainty bands); ``covered_sizes_mm`` (smallest and largest rock
    size of the DEM statistics, mm: the size below which
    :class:`msmill.model.providers.HeldBelow` holds them).
    """

    @property
    def n_stages(self) -> int:
        """Number of stages the parameters describe."""
        ...

    def stage_parameters(
        self, sizes_mm: np.ndarray, stage_speeds_rpm: list[float] | None = None,
        feed_tph: float | None = None, gate_deg: float | None = None,
    ) -> StageParameters:
        """Parameters at ``sizes_mm`` (mm) for the given operating point (warns off-point)."""
        ...
