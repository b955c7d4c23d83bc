"""Circuit units: small registered classes behind one interface (:class:`Unit`).

Every stream of a circuit is a vector of mass flow per size class of the
circuit's :class:`~msmill.psd.SizeGrid` (t/h), or a stack of them (K, N), one row
per posterior sample, when the circuit's uncertainty band is solved. A unit has named outlets and at
most one inlet, ``"feed"`` (streams into it are summed); :meth:`Unit.apply`
maps the inlet's flow to the outlets' flows. Units are registered by type name
in :data:`UNITS` (:func:`register_unit`); a circuit file names them by type
(``msmill.model.circuit.file``).

Shipped units:

* ``feed`` (:class:`FreshFeed`): a fresh feed, rate (t/h) and PSD.
* ``product`` (:class:`Product`): where a circuit product leaves.
* ``screen`` (:class:`Screen`): the Whiten efficiency curve with fish-hook and bypass.
* ``splitter`` (:class:`Splitter`): fixed fractions, every size alike.
* ``mill`` (:class:`MillUnit`): the multi-shaft mill (:class:`msmill.model.Mill`, any provider and sub-models).
* ``breakage_matrix`` (:class:`BreakageMatrixMill`): a mill given as a fixed breakage matrix
  (product = B feed), e.g. for analytic checks or a mill measured elsewhere.
"""

from __future__ import annotations

import math
import warnings
from abc import ABC, abstractmethod
from typing import Any, ClassVar

import numpy as np

from msmill.errors import MsmillInputError
from msmill.psd import PSD, SizeGrid

#: Unit classes by type name (``type = "..."`` in a circuit file).
UNITS: dict[str, type[Unit]] = {}


def register_unit(cls: type[Unit]) -> type[Unit]:
    """Class decorator: register a :class:`Unit` subclass under its ``type_name``."""
    UNITS[cls.type_name] = cls
    return cls


class Unit(ABC):
    """One unit of a circuit.

    Class attributes
    ----------------
    type_name : str
        Registry name.
    has_inlet : bool
        Whether streams can enter (``"feed"``); a fresh feed has none.
    breaks_rock : bool
        Whether the unit makes finer rock; every recycle loop must hold one
        (a loop of screens and splitters alone only holds rock back).

    Attributes
    ----------
    name : str
        Unit name, unique in its circuit.
    outlets : tuple of str
        Outlet names (streams leave from ``"unit.outlet"``).
    """

    type_name: ClassVar[str] = ""
    has_inlet: ClassVar[bool] = True
    breaks_rock: ClassVar[bool] = False

    def __init__(self, name: str, outlets: tuple[str, ...]) -> None:
        self.name = name
        self.outlets = tuple(outlets)
        self.grid: SizeGrid | None = None

    def bind(self, grid: SizeGrid) -> None:
        """Put the unit on the circuit's size grid (called once before solving)."""
        self.grid = grid

    @abstractmethod
    def apply(self, feed_tph: np.ndarray) -> dict[str, np.ndarray]:
        """Outlet flows (t/h per size class) for the inlet flow ``feed_tph`` (t/h per size class, (N,) or (K, N))."""

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r})"


@register_unit
class FreshFeed(Unit):
    """A fresh feed: ``rate_tph`` (t/h) of ``psd``; outlet ``"out"``."""

    type_name = "feed"
    has_inlet = False

    def __init__(self, name: str, rate_tph: float, psd: PSD) -> None:
        super().__init__(name, ("out",))
        if not (isinstance(rate_tph, int | float) and math.isfinite(rate_tph) and rate_tph > 0):
            raise MsmillInputError(f"{name}.rate_tph", rate_tph, "a feed rate > 0 t/h")
        self.rate_tph = float(rate_tph)
        self.psd = psd
        self._flow: np.ndarray | None = None

    @property
    def top_mm(self) -> float:
        """Top size of the feed (mm)."""
        return float(self.psd.grid.edges_mm[-1])

    def bind(self, grid: SizeGrid) -> None:
        super().bind(grid)
        psd = self.psd.rebin(grid) if self.psd.grid != grid else self.psd
        self._flow = self.rate_tph * psd.fractions

    def apply(self, feed_tph: np.ndarray) -> dict[str, np.ndarray]:
        return {"out": self._flow.copy()}


@register_unit
class Product(Unit):
    """A circuit product: the streams into it leave the circuit (no outlets)."""

    type_name = "product"

    def __init__(self, name: str) -> None:
        super().__init__(name, ())

    def apply(self, feed_tph: np.ndarray) -> dict[str, np.ndarray]:
        return {}


def whiten_beta_star(alpha: float, beta: float) -> float:
    """Whiten's ``beta*``: the scale that puts the classified fine partition at 1/2 at ``d = d50c``.

    Solves ``(1 + beta beta*) (e^alpha - 1) = (e^(alpha beta*) + e^alpha - 2) / 2`` (``beta*`` = 1 at
    ``beta`` = 0).
    """
    if beta == 0.0 or math.isinf(alpha):
        return 1.0
    from scipy.optimize import brentq

    ea = math.expm1(alpha)

    def f(bs: float) -> float:
        return (1.0 + beta * bs) * ea - 0.5 * (math.exp(alpha * bs) + ea - 1.0)

    if f(1.0) <= 0.0:  # f(1) = beta (e^alpha - 1) > 0 in exact arithmetic; a tiny beta rounds it away
        return 1.0
    hi = 2.0
    while f(hi) > 0.0:
        hi *= 2.0
    return float(brentq(f, 1.0, hi, xtol=1e-14))


def whiten_fine_partition(x: np.ndarray, alpha: float, beta: float, bypass: float) -> np.ndarray:
    """Fraction of each size reporting to the undersize (fines), Whiten's efficiency curve.

    ``E(x) = (1 - bypass) (1 + beta beta* x) (e^alpha - 1) / (e^(alpha beta* x) + e^alpha - 2)``
    with ``x = d / d50c``: ``1 - bypass`` at ``x = 0``, ``(1 - bypass) / 2`` at ``x = 1``, 0 for
    coarse rock; ``beta > 0`` gives the fish-hook (a dip of the oversize partition at fine sizes);
    ``bypass`` is the fraction of the feed that goes to the oversize unclassified. ``alpha = inf``
    is the ideal screen: ``1 - bypass`` below ``d50c``, half at it, 0 above.
    """
    x = np.asarray(x, dtype=float)
    c = 1.0 - bypass
    if math.isinf(alpha):
        return c * np.where(x < 1.0, 1.0, np.where(x == 1.0, 0.5, 0.0))
    bs = whiten_beta_star(alpha, beta)
    with np.errstate(over="ignore"):
        den = np.exp(alpha * bs * x) + math.expm1(alpha) - 1.0
    return c * (1.0 + beta * bs * x) * math.expm1(alpha) / den


@register_unit
class Screen(Unit):
    """A screen (one deck) with Whiten's efficiency curve; outlets ``"oversize"`` and ``"undersize"``.

    Parameters
    ----------
    name : str
    d50c_mm : float
        Corrected cut size (mm): half of the classified rock of this size passes.
    alpha : float
        Sharpness (> 0; ``inf``: an ideal screen).
    beta : float
        Fish-hook (>= 0; 0: none).
    bypass : float
        Fraction of the feed that goes to the oversize unclassified (0 <= bypass < 1).

    Each size class is classified at its representative size (``SizeGrid.mids_mm``).
    Decks in series are screens in series (the oversize of one feeds the next).
    """

    type_name = "screen"

    def __init__(self, name: str, d50c_mm: float, alpha: float = 4.0, beta: float = 0.0,
                 bypass: float = 0.0) -> None:
        super().__init__(name, ("oversize", "undersize"))
        from msmill.validate import number

        self.d50c_mm = number(d50c_mm, f"{name}.d50c_mm", unit="mm", gt=0)
        if not (isinstance(alpha, int | float) and alpha > 0 and not math.isnan(alpha)):
            raise MsmillInputError(f"{name}.alpha", alpha, "a sharpness > 0 (inf: an ideal screen)")
        self.alpha = float(alpha)
        self.beta = number(beta, f"{name}.beta", ge=0, le=50)
        self.bypass = number(bypass, f"{name}.bypass", ge=0, lt=1)
        peak = float(whiten_fine_partition(np.linspace(0.0, 2.0, 2001), self.alpha, self.beta, self.bypass).max())
        if peak > 1.0 + 1e-12:
            raise MsmillInputError(f"{name}.beta", beta, f"a fish-hook that sends at most all of a size to the "
                                   f"undersize (here {peak:.3g}); lower beta or raise bypass")
        self.fine_partition: np.ndarray | None = None

    def bind(self, grid: SizeGrid) -> None:
        super().bind(grid)
        self.fine_partition = np.clip(
            whiten_fine_partition(grid.mids_mm / self.d50c_mm, self.alpha, self.beta, self.bypass), 0.0, 1.0)

    def apply(self, feed_tph: np.ndarray) -> dict[str, np.ndarray]:
        fine = self.fine_partition * feed_tph
        return {"oversize": feed_tph - fine, "undersize": fine}


@register_unit
class Splitter(Unit):
    """Fixed split of the feed, every size alike: ``fractions`` {outlet: fraction}, summing to 1."""

    type_name = "splitter"

    def __init__(self, name: str, fractions: dict[str, float]) -> None:
        if not isinstance(fractions, dict) or len(fractions) < 2:
            raise MsmillInputError(f"{name}.fractions", fractions, "a table of two or more {outlet = fraction}")
        from msmill.validate import number

        fr = {str(k): number(v, f"{name}.fractions.{k}", ge=0, le=1) for k, v in fractions.items()}
        if abs(sum(fr.values()) - 1.0) > 1e-9:
            raise MsmillInputError(f"{name}.fractions", fractions, "fractions that sum to 1")
        super().__init__(name, tuple(fr))
        self.fractions = fr

    def apply(self, feed_tph: np.ndarray) -> dict[str, np.ndarray]:
        return {k: f * feed_tph for k, f in self.fractions.items()}


@register_unit
class BreakageMatrixMill(Unit):
    """A mill as a fixed breakage matrix: product = ``matrix @ feed``; outlet ``"product"``.

    ``matrix[i, j]``: mass fraction of feed class ``j`` that leaves in class ``i`` (circuit grid,
    classes fine to coarse): non-negative, columns sum to 1, nothing above the parent class.
    """

    type_name = "breakage_matrix"
    breaks_rock = True

    def __init__(self, name: str, matrix: Any) -> None:
        super().__init__(name, ("product",))
        try:
            B = np.asarray(matrix, dtype=float)
        except (TypeError, ValueError):
            raise MsmillInputError(f"{name}.matrix", matrix, "a square table of numbers") from None
        if B.ndim != 2 or B.shape[0] != B.shape[1] or not np.all(np.isfinite(B)) or np.any(B < 0):
            raise MsmillInputError(f"{name}.matrix", f"shape {B.shape}", "a square matrix of finite numbers >= 0")
        if np.any(np.triu(B.T, 1) > 0):  # B[i, j] > 0 with i > j: mass above its parent
            raise MsmillInputError(f"{name}.matrix", "mass above its parent class",
                                   "matrix[i][j] = 0 for i > j (classes fine to coarse)")
        if np.any(np.abs(B.sum(axis=0) - 1.0) > 1e-9):
            raise MsmillInputError(f"{name}.matrix", "column sums " + ", ".join(f"{v:.4g}" for v in B.sum(axis=0)),
                                   "columns that sum to 1 (mass conserved)")
        self.matrix = B

    def bind(self, grid: SizeGrid) -> None:
        if grid.n_classes != self.matrix.shape[0]:
            raise MsmillInputError(f"{self.name}.matrix", f"{self.matrix.shape[0]} classes",
                                   f"{grid.n_classes} classes (the circuit grid's)")
        super().bind(grid)

    def apply(self, feed_tph: np.ndarray) -> dict[str, np.ndarray]:
        return {"product": feed_tph @ self.matrix.T}


#: A circuit's steady state is accepted once every mill's operators were built within this relative
#: difference of its feed rate (:meth:`msmill.model.circuit.Circuit.solve`).
RATE_TOL = 1e-6


@register_unit
class MillUnit(Unit):
    """The multi-shaft mill in a circuit; outlet ``"product"``.

    Parameters
    ----------
    name : str
    mill : msmill.model.Mill
        Any provider and sub-models; its grid is set to the circuit's. Expected-value solver only.
    operating : dict
        :class:`msmill.machine.OperatingPoint` fields but the feed rate (``speed_rpm`` or
        ``stage_speeds_rpm``, ``bottom_speed_factor``, ``gate_deg``).

    At a given feed rate the mill's steady state is linear in its feed, so the unit holds the
    transfer matrix ``T`` (:meth:`transfer_matrix`: product t/h per class for 1 t/h of feed in each
    class) built at :attr:`operator_rate_tph` and applies it to whatever it is fed. The circuit solver
    converges the streams with ``T`` fixed, then :meth:`rebuild` s it at the mill's new feed rate,
    until the two rates agree within :data:`RATE_TOL`.

    For the circuit's uncertainty band the unit carries :attr:`samples` (a :class:`SampleTransfers`):
    one transfer matrix per posterior sample at two feed rates, interpolated linearly at each
    sample's own feed rate; the feed is then (K, N), one row per sample.
    """

    type_name = "mill"
    breaks_rock = True

    def __init__(self, name: str, mill: Any, operating: dict[str, Any]) -> None:
        super().__init__(name, ("product",))
        if mill.solver.name != "expected_value":
            raise MsmillInputError(f"{name}.model.solver", mill.solver.name, "expected_value (circuits solve the "
                                   "mill's steady state many times)")
        self.mill = mill
        self.operating = dict(operating)
        self.operator_rate_tph: float | None = None
        self.transfer: np.ndarray | None = None
        self.rebuilds = 0
        self.build_warnings: list[tuple[Any, type]] = []
        self.samples: SampleTransfers | None = None

    def operating_point(self, feed_tph: float) -> Any:
        """The mill's :class:`~msmill.machine.OperatingPoint` at ``feed_tph`` (t/h)."""
        from msmill.machine import OperatingPoint

        return OperatingPoint(**{**self.operating, "feed_tph": float(feed_tph)})

    def bind(self, grid: SizeGrid) -> None:
        super().bind(grid)
        self.mill.grid = grid
        self.operator_rate_tph = self.transfer = self.samples = None
        self.rebuilds = 0

    def rate_mismatch(self, feed_tph: float) -> float:
        """Relative difference between ``feed_tph`` and the rate the operators were built at."""
        r0 = self.operator_rate_tph
        return 0.0 if r0 is None or feed_tph <= 0 else abs(feed_tph - r0) / r0

    def transfer_matrix(self, feed_tph: float) -> np.ndarray:
        """Transfer matrix ``T`` (N, N) at ``feed_tph``: steady product per class per unit feed per class.

        Built from the assembled mill (:meth:`msmill.model.Mill.prepare`, cached by operating point):
        ``T = P (I - M)^-1 F`` with ``F`` the undamaged feed of each class into the feed compartment,
        ``P`` the product operator; one sparse LU factorisation, N right-hand sides. Columns sum to 1.
        """
        import scipy.sparse as sp
        import scipy.sparse.linalg as spla

        lm = self.mill.prepare(self.grid, self.operating_point(feed_tph))[3]
        F = np.column_stack([lm.feed_vector(e, 1.0) for e in np.eye(lm.n_sizes)])
        lu = spla.splu((sp.identity(lm.n_state, format="csc") - lm.M.tocsc()).tocsc(), permc_spec="MMD_AT_PLUS_A")
        X = np.maximum(lu.solve(F), 0.0)
        return np.asarray(lm.out_op @ X)

    def rebuild(self, feed_tph: float) -> None:
        """Build the operators at ``feed_tph`` (t/h); their warnings are kept in :attr:`build_warnings`
        (the circuit solver gives those of the last build, the one at the mill's own feed rate)."""
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            self.transfer = self.transfer_matrix(feed_tph)
        self.build_warnings = [(w.message, w.category) for w in caught]
        self.operator_rate_tph = float(feed_tph)
        self.rebuilds += 1

    def apply(self, feed_tph: np.ndarray) -> dict[str, np.ndarray]:
        if self.samples is not None:
            return {"product": self.samples.apply(feed_tph)}
        rate = float(np.sum(feed_tph))
        if self.transfer is None:
            if rate <= 0.0:
                return {"product": np.zeros_like(feed_tph)}
            self.rebuild(rate)
        return {"product": feed_tph @ self.transfer.T}


class SampleTransfers:
    """Transfer matrices of K posterior samples of a mill at several feed rates, interpolated in rate.

    Parameters
    ----------
    rates_tph : sequence of float (R,)
        Ascending feed rates (t/h) the matrices were built at (one rate: no rate dependence).
    transfers : ndarray (R, K, N, N)
        Sample ``k``'s transfer matrix at each rate.

    :meth:`apply` feeds sample ``k`` (row ``k`` of a (K, N) feed) through its matrix interpolated
    piecewise linearly at its own feed rate (the end segments extended beyond the rates); columns
    still sum to 1, as every built matrix's do.
    """

    def __init__(self, rates_tph: Any, transfers: np.ndarray) -> None:
        self.rates_tph = np.asarray(rates_tph, dtype=float)
        self.transfers = np.asarray(transfers, dtype=float)

    def apply(self, feed_tph: np.ndarray) -> np.ndarray:
        r = self.rates_tph
        if r.size == 1:
            return np.einsum("kij,kj->ki", self.transfers[0], feed_tph)
        rate = np.sum(feed_tph, axis=-1)
        j = np.clip(np.searchsorted(r, rate) - 1, 0, r.size - 2)  # segment of each sample
        w = (rate - r[j]) / (r[j + 1] - r[j])
        k = np.arange(rate.size)
        T = self.transfers[j, k] + w[:, None, None] * (self.transfers[j + 1, k] - self.transfers[j, k])
        return np.einsum("kij,kj->ki", T, feed_tph)
