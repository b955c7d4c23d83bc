"""Size grids and particle size distributions (PSDs).

A :class:`SizeGrid` is a set of ascending sieve edges in mm. Class ``i`` spans
``[edges_mm[i], edges_mm[i + 1])``; class 0 also holds everything finer than
``edges_mm[0]`` (the "pan"), so mass is conserved down to zero size. Material
coarser than the top edge has no class: loaders lump it into the top class
(documented per function) so that mass is always conserved.

A :class:`PSD` is a vector of mass fractions per class (sum 1). Its cumulative
% passing is defined at ``edges_mm[1:]``: passing at ``edges_mm[k]`` is the sum
of the classes below ``k`` (so passing at the top edge is 100 %).

Interpolation convention
------------------------
``passing_at`` interpolates the cumulative curve linearly in ``ln(size)``
through the knots ``(edges_mm[0], 0 %), (edges_mm[1], P_1), ...,
(edges_mm[n], 100 %)``: for reading the curve the pan is assumed to lie inside
class 0 (choose ``edges_mm[0]`` fine enough that this matters little). Below
``edges_mm[0]`` passing is 0 %, above the top edge it is 100 %. Percentiles are
the inverse of the same curve. All operations are numpy-vectorised: no Python
loop runs over size classes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from msmill.errors import MsmillInputError

if TYPE_CHECKING:
    import pandas as pd

__all__ = [
    "PSD",
    "SQRT2_SIEVES_MM",
    "FitResult",
    "SizeGrid",
    "ks_statistic",
]

#: Tolerance on the sum of mass fractions (absolute).
FRACTION_SUM_TOL = 1e-6
#: Tolerance (in % passing) for small violations of 0-100 and monotonicity.
PASSING_TOL = 1e-9


def _as_float_array(value: Any, field_name: str) -> NDArray[np.float64]:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise MsmillInputError(field_name, value, "an array of numbers") from exc
    return arr


def _check_sizes(sizes: Any, field_name: str, min_len: int = 1) -> NDArray[np.float64]:
    arr = _as_float_array(sizes, field_name)
    if arr.ndim != 1 or arr.size < min_len:
        raise MsmillInputError(field_name, sizes, f"a 1-D list of at least {min_len} sizes in mm")
    if not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        raise MsmillInputError(field_name, sizes, "finite sizes > 0 mm")
    if arr.size > 1 and np.any(np.diff(arr) <= 0):
        raise MsmillInputError(field_name, sizes, "strictly increasing sizes")
    return arr


#: The standard sqrt(2) sieve series (ISO 565 R 40/3 principal sizes, as circuit stream tables
#: are read), mm.
SQRT2_SIEVES_MM = (0.038, 0.053, 0.075, 0.106, 0.15, 0.212, 0.3, 0.425, 0.6, 0.85, 1.18, 1.7, 2.36, 3.35,
                   4.75, 6.7, 9.5, 13.2, 19.0, 26.5, 37.5, 53.0, 75.0, 106.0, 150.0)


class SizeGrid:
    """Ascending sieve edges in mm defining ``n`` size classes.

    Parameters
    ----------
    edges_mm : array_like
        ``n + 1`` strictly increasing edges (mm, all > 0), ``n >= 1``.

    Notes
    -----
    Class ``i`` spans ``[edges_mm[i], edges_mm[i+1])``; class 0 also holds all
    material finer than ``edges_mm[0]``. The grid is immutable and hashable.
    """

    __slots__ = ("_edges", "_hash", "_mids")

    def __init__(self, edges_mm: ArrayLike) -> None:
        edges = _check_sizes(edges_mm, "edges_mm", min_len=2).copy()
        edges.setflags(write=False)
        self._edges = edges
        mids = np.sqrt(edges[:-1] * edges[1:])
        mids.setflags(write=False)
        self._mids = mids
        self._hash: int | None = None

    @classmethod
    def geometric(cls, min_mm: float, max_mm: float, ratio: float = math.sqrt(2)) -> SizeGrid:
        """Geometric sieve series ``min_mm * ratio**k`` (default the sqrt(2) series).

        Parameters
        ----------
        min_mm : float
            Lowest edge (mm, > 0).
        max_mm : float
            Size the series must reach (mm, > ``min_mm``). The top edge is the
            first member of the series ``>= max_mm`` (within 1e-9 relative).
        ratio : float, optional
            Ratio between consecutive edges (> 1), default ``sqrt(2)``.
        """
        for name, v in (("min_mm", min_mm), ("max_mm", max_mm), ("ratio", ratio)):
            if (isinstance(v, bool) or not isinstance(v, int | float | np.floating | np.integer)
                    or not math.isfinite(v)):
                raise MsmillInputError(name, v, "a finite number")
        if min_mm <= 0:
            raise MsmillInputError("min_mm", min_mm, "a size > 0 mm")
        if max_mm <= min_mm:
            raise MsmillInputError("max_mm", max_mm, f"a size > min_mm ({min_mm} mm)")
        if ratio <= 1:
            raise MsmillInputError("ratio", ratio, "a number > 1")
        n = max(1, math.ceil(math.log(max_mm / min_mm) / math.log(ratio) - 1e-9))
        if n > 10_000:
            raise MsmillInputError("ratio", ratio, "a ratio giving at most 10000 classes")
        return cls(min_mm * float(ratio) ** np.arange(n + 1))

    @property
    def edges_mm(self) -> NDArray[np.float64]:
        """Class edges (mm), read-only, shape ``(n_classes + 1,)``."""
        return self._edges

    @property
    def n_classes(self) -> int:
        """Number of size classes."""
        return int(self._edges.size - 1)

    @property
    def mids_mm(self) -> NDArray[np.float64]:
        """Geometric mean of each class's edges (mm): the representative rock size."""
        return self._mids

    @property
    def lower_mm(self) -> NDArray[np.float64]:
        """Lower edge of each class (mm)."""
        return self._edges[:-1]

    @property
    def upper_mm(self) -> NDArray[np.float64]:
        """Upper edge of each class (mm)."""
        return self._edges[1:]

    def class_of(self, size_mm: ArrayLike) -> NDArray[np.intp]:
        """Index of the class holding each size (finer than the grid → 0, coarser → top).

        Parameters
        ----------
        size_mm : array_like
            Sizes (mm).
        """
        s = np.asarray(size_mm, dtype=float)
        idx = np.searchsorted(self._edges, s, side="right") - 1
        return np.clip(idx, 0, self.n_classes - 1)

    def __len__(self) -> int:
        return self.n_classes

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, SizeGrid):
            return NotImplemented
        return self._edges.shape == other._edges.shape and bool(
            np.array_equal(self._edges, other._edges)
        )

    def __hash__(self) -> int:
        if self._hash is None:
            self._hash = hash(self._edges.tobytes())
        return self._hash

    def __repr__(self) -> str:
        e = self._edges
        return f"SizeGrid(n_classes={self.n_classes}, {e[0]:.4g}-{e[-1]:.4g} mm)"


@dataclass(frozen=True)
class FitResult:
    """Result of fitting a model to a cumulative passing curve.

    Attributes
    ----------
    model : str
        ``"rosin_rammler"`` or ``"gates_gaudin_schuhmann"``.
    params : dict[str, float]
        Rosin-Rammler: ``x63_mm`` (size at 63.2 % passing), ``n`` (spread).
        GGS: ``k_mm`` (size modulus, 100 % passing), ``m`` (distribution modulus).
    r_squared : float
        Coefficient of determination on the fitted points (% passing).
    rmse_pct : float
        Root-mean-square residual (% passing).
    n_points : int
        Number of points fitted.
    """

    model: str
    params: dict[str, float]
    r_squared: float
    rmse_pct: float
    n_points: int
    extra: dict[str, Any] = field(default_factory=dict)


class PSD:
    """Mass fractions of material per class of a :class:`SizeGrid`.

    Parameters
    ----------
    grid : SizeGrid
        The size grid.
    fractions : array_like
        Mass fraction per class, shape ``(n_classes,)``, each >= 0 (tiny
        negatives down to -1e-12 are clipped), summing to 1 within
        :data:`FRACTION_SUM_TOL`; the stored vector is renormalised to sum 1.
    validate : bool, optional
        Skip validation when ``False`` (for trusted, already normalised vectors
        in hot paths). Default ``True``.
    """

    __slots__ = ("_fractions", "_grid", "_passing")

    def __init__(self, grid: SizeGrid, fractions: ArrayLike, *, validate: bool = True) -> None:
        if not isinstance(grid, SizeGrid):
            raise MsmillInputError("grid", grid, "a msmill.psd.SizeGrid")
        f = np.array(fractions, dtype=float)  # copy
        if validate:
            if f.shape != (grid.n_classes,):
                raise MsmillInputError(
                    "fractions", fractions, f"{grid.n_classes} mass fractions (one per class)"
                )
            if not np.all(np.isfinite(f)) or np.any(f < -1e-12):
                raise MsmillInputError("fractions", fractions, "finite mass fractions >= 0")
            total = float(f.sum())
            if abs(total - 1.0) > FRACTION_SUM_TOL:
                raise MsmillInputError(
                    "fractions", fractions, f"mass fractions summing to 1 (sum is {total:.6g})"
                )
            np.clip(f, 0.0, None, out=f)
            f /= f.sum()
        f.setflags(write=False)
        self._grid = grid
        self._fractions = f
        self._passing: NDArray[np.float64] | None = None

    # ------------------------------------------------------------------ basics
    @property
    def grid(self) -> SizeGrid:
        """The size grid."""
        return self._grid

    @property
    def fractions(self) -> NDArray[np.float64]:
        """Mass fraction per class (read-only), sums to 1."""
        return self._fractions

    @property
    def sizes_mm(self) -> NDArray[np.float64]:
        """Sieve sizes at which cumulative passing is defined: ``edges_mm[1:]`` (mm)."""
        return self._grid.edges_mm[1:]

    @property
    def passing_pct(self) -> NDArray[np.float64]:
        """Cumulative % passing at :attr:`sizes_mm` (last value 100)."""
        if self._passing is None:
            p = np.cumsum(self._fractions) * 100.0
            p[-1] = 100.0
            np.minimum(p, 100.0, out=p)
            p.setflags(write=False)
            self._passing = p
        return self._passing

    def _knots(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        logx = np.log(self._grid.edges_mm)
        p = np.concatenate(([0.0], self.passing_pct))
        return logx, p

    # ------------------------------------------------------------ constructors
    @classmethod
    def from_passing(
        cls,
        sizes_mm: ArrayLike,
        passing_pct: ArrayLike,
        grid: SizeGrid | None = None,
        *,
        prefix: str = "",
    ) -> PSD:
        """Build a PSD from a cumulative % passing table.

        Parameters
        ----------
        sizes_mm : array_like
            Sieve sizes (mm), > 0, strictly increasing, at least 2.
        passing_pct : array_like
            Cumulative % passing at each size, within 0-100, non-decreasing.
        grid : SizeGrid, optional
            Target grid. If omitted, the grid's edges ``[1:]`` are the table's
            sizes and ``edges_mm[0]`` extends the table one step (the ratio of
            its first two sizes) below; if the last passing value is below
            100 %, one more edge is added above (same ratio as the last two
            sizes) for the oversize. If given, the table is read at the grid's
            edges with :meth:`passing_at`-style log interpolation; material
            coarser than the grid's top edge is lumped into the top class.
        prefix : str, optional
            Prepended to the field names in errors and warnings (e.g. ``run.toml.feed.``).

        Returns
        -------
        PSD

        Raises
        ------
        MsmillInputError
            For sizes not increasing, % passing outside 0-100 or decreasing, or
            given as fractions (all <= 1). A table ending below 100 % warns
            (:class:`msmill.validate.InputWarning`) with the oversize mass.
        """
        from msmill.validate import passing

        x = _check_sizes(sizes_mm, f"{prefix}size_mm", min_len=2)
        # 0-100 %, non-decreasing, not fractions; a last value below 100 % warns (oversize class)
        p = passing(passing_pct, f"{prefix}passing_pct", x.size, tol=PASSING_TOL)
        p = np.clip(np.maximum.accumulate(p), 0.0, 100.0)
        if grid is None:
            lo = x[0] * x[0] / x[1]
            edges = np.concatenate(([lo], x))
            cum = p
            if cum[-1] < 100.0 - PASSING_TOL:
                edges = np.concatenate((edges, [x[-1] * x[-1] / x[-2]]))
                cum = np.concatenate((cum, [100.0]))
            grid = SizeGrid(edges)
        else:
            if not isinstance(grid, SizeGrid):
                raise MsmillInputError("grid", grid, "a msmill.psd.SizeGrid")
            # table's own curve: knot below the first size at 0 % one step down
            lo = x[0] * x[0] / x[1]
            logx = np.log(np.concatenate(([lo], x)))
            pk = np.concatenate(([0.0], p))
            if p[0] <= 0.0:
                logx, pk = logx[1:], pk[1:]
            cum = np.interp(np.log(grid.edges_mm[1:]), logx, pk, left=0.0, right=100.0)
            cum[-1] = 100.0
        f = np.diff(np.concatenate(([0.0], cum))) / 100.0
        f = np.clip(f, 0.0, None)
        f /= f.sum()
        return cls(grid, f, validate=False)

    @classmethod
    def from_frame(cls, frame: pd.DataFrame, grid: SizeGrid | None = None) -> PSD:
        """Build a PSD from a DataFrame with ``size_mm`` and ``passing_pct`` columns.

        Rows are sorted by size first; see :meth:`from_passing` for ``grid``. msmill's own per-class
        product table (``msmill predict``'s ``*_product.csv``: ``upper_mm`` and ``product_passing_pct``)
        is read as the product's passing at each class's upper edge.
        """
        import pandas as pd

        if not isinstance(frame, pd.DataFrame):
            raise MsmillInputError("frame", type(frame).__name__, "a pandas DataFrame")
        if "size_mm" not in frame.columns and {"upper_mm", "product_passing_pct"} <= set(frame.columns):
            frame = frame.rename(columns={"upper_mm": "size_mm", "product_passing_pct": "passing_pct"})
        missing = [c for c in ("size_mm", "passing_pct") if c not in frame.columns]
        if missing:
            raise MsmillInputError(
                "columns", list(frame.columns), "columns 'size_mm' and 'passing_pct'"
            )
        df = frame[["size_mm", "passing_pct"]]
        for col in df.columns:
            vals = pd.to_numeric(df[col], errors="coerce")
            if vals.isna().any():
                bad = df[col][vals.isna()].iloc[0]
                raise MsmillInputError(col, bad, "numbers (no blanks)")
        df = df.astype(float).sort_values("size_mm", kind="stable")
        return cls.from_passing(df["size_mm"].to_numpy(), df["passing_pct"].to_numpy(), grid)

    @classmethod
    def read_csv(cls, path: str | Path, grid: SizeGrid | None = None) -> PSD:
        """Read a cumulative % passing table (CSV columns ``size_mm``, ``passing_pct``).

        Lines starting with ``#`` are comments.
        """
        from msmill.validate import read_csv

        return cls.from_frame(read_csv(path, "path", "PSD CSV file"), grid)

    @classmethod
    def single_class(cls, grid: SizeGrid, size_mm: float) -> PSD:
        """All mass in the class holding ``size_mm`` (mm)."""
        f = np.zeros(grid.n_classes)
        f[int(grid.class_of(size_mm))] = 1.0
        return cls(grid, f, validate=False)

    @classmethod
    def mix(cls, psds: Sequence[PSD], weights: ArrayLike) -> PSD:
        """Mass-weighted mixture of PSDs on one grid (weights are normalised, >= 0)."""
        if not psds:
            raise MsmillInputError("psds", psds, "at least one PSD")
        grid = psds[0].grid
        if any(p.grid != grid for p in psds):
            raise MsmillInputError("psds", "grids differ", "PSDs on the same SizeGrid (rebin first)")
        w = _as_float_array(weights, "weights")
        if w.shape != (len(psds),) or np.any(~np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
            raise MsmillInputError("weights", weights, f"{len(psds)} weights >= 0 with sum > 0")
        f = (w / w.sum()) @ np.stack([p.fractions for p in psds])
        return cls(grid, f, validate=False)

    # ---------------------------------------------------------------- outputs
    def to_frame(self) -> pd.DataFrame:
        """Cumulative passing table: columns ``size_mm`` (``edges_mm[1:]``), ``passing_pct``."""
        import pandas as pd

        return pd.DataFrame({"size_mm": self.sizes_mm, "passing_pct": self.passing_pct})

    def class_table(self) -> pd.DataFrame:
        """Per-class table: ``lower_mm``, ``upper_mm``, ``mid_mm``, ``mass_fraction``, ``passing_pct``."""
        import pandas as pd

        g = self._grid
        return pd.DataFrame(
            {
                "lower_mm": g.lower_mm,
                "upper_mm": g.upper_mm,
                "mid_mm": g.mids_mm,
                "mass_fraction": self._fractions,
                "passing_pct": self.passing_pct,
            }
        )

    def to_csv(self, path: str | Path) -> None:
        """Write :meth:`to_frame` as CSV (readable by :meth:`read_csv`)."""
        self.to_frame().to_csv(path, index=False)

    # ---------------------------------------------------------- interpolation
    def passing_at(self, size_mm: ArrayLike) -> NDArray[np.float64] | float:
        """Cumulative % passing at arbitrary sizes, interpolated in log size.

        Parameters
        ----------
        size_mm : array_like
            Sizes (mm, > 0).

        Returns
        -------
        float or ndarray
            % passing (0-100), same shape as ``size_mm``.
        """
        s = _as_float_array(size_mm, "size_mm")
        if np.any(~(s > 0)):
            raise MsmillInputError("size_mm", size_mm, "sizes > 0 mm")
        logx, p = self._knots()
        out = np.interp(np.log(s), logx, p, left=0.0, right=100.0)
        return float(out) if out.ndim == 0 else out

    def percentile(self, pct: ArrayLike) -> NDArray[np.float64] | float:
        """Size (mm) below which ``pct`` % of the mass passes (e.g. 80 → P80).

        The smallest size at which the log-interpolated curve reaches ``pct``.

        Parameters
        ----------
        pct : array_like
            Percent passing, each in (0, 100].
        """
        q = _as_float_array(pct, "pct")
        if np.any(~((q > 0) & (q <= 100))):
            raise MsmillInputError("pct", pct, "percent passing in (0, 100]")
        logx, p = self._knots()
        k = np.searchsorted(p, q, side="left")  # first knot with p >= q, k >= 1
        k = np.clip(k, 1, p.size - 1)
        p0, p1 = p[k - 1], p[k]
        span = p1 - p0
        t = np.where(span > 0, (q - p0) / np.where(span > 0, span, 1.0), 1.0)
        out = np.exp(logx[k - 1] + t * (logx[k] - logx[k - 1]))
        return float(out) if out.ndim == 0 else out

    @property
    def p50_mm(self) -> float:
        """Median size P50 (mm)."""
        return float(self.percentile(50.0))

    @property
    def p80_mm(self) -> float:
        """P80 (mm): 80 % of the mass passes this size."""
        return float(self.percentile(80.0))

    def rebin(self, grid: SizeGrid) -> PSD:
        """Re-bin onto another grid, conserving mass.

        The cumulative curve is read at the new edges (log interpolation); the
        new class 0 takes everything below its upper edge and material coarser
        than the new top edge is lumped into the new top class.
        """
        if not isinstance(grid, SizeGrid):
            raise MsmillInputError("grid", grid, "a msmill.psd.SizeGrid")
        if grid == self._grid:
            return self
        logx, p = self._knots()
        cum = np.interp(np.log(grid.edges_mm[1:]), logx, p, left=0.0, right=100.0)
        cum[-1] = 100.0
        f = np.diff(np.concatenate(([0.0], cum))) / 100.0
        np.clip(f, 0.0, None, out=f)
        f /= f.sum()
        return PSD(grid, f, validate=False)

    # ------------------------------------------------------------------ fits
    def _fit_points(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        x, p = self.sizes_mm, self.passing_pct
        keep = (p > 1e-9) & (p < 100.0 - 1e-9)
        if keep.sum() < 2:
            raise MsmillInputError(
                "psd", "fewer than 2 points strictly between 0 and 100 % passing",
                "a PSD spread over at least 3 classes to fit a distribution",
            )
        return x[keep], p[keep]

    def fit_rosin_rammler(self) -> FitResult:
        """Least-squares Rosin-Rammler fit ``P = 100 (1 - exp(-(x/x63)^n))``.

        Fitted to the points strictly between 0 and 100 % passing, residuals
        in % passing (``scipy.optimize.least_squares``).
        """
        from scipy.optimize import least_squares

        x, p = self._fit_points()
        lx = np.log(x)
        yl = np.log(-np.log1p(-p / 100.0))
        n0, c0 = np.polyfit(lx, yl, 1)
        n0 = max(float(n0), 0.05)
        x63_0 = float(np.exp(-c0 / n0))

        def resid(theta: NDArray[np.float64]) -> NDArray[np.float64]:
            lx63, ln_n = theta
            n = np.exp(ln_n)
            return 100.0 * (1.0 - np.exp(-np.exp(n * (lx - lx63)))) - p

        sol = least_squares(resid, [math.log(x63_0), math.log(n0)], method="lm")
        x63, n = float(np.exp(sol.x[0])), float(np.exp(sol.x[1]))
        return _fit_result("rosin_rammler", {"x63_mm": x63, "n": n}, sol.fun, p)

    def fit_gates_gaudin_schuhmann(self) -> FitResult:
        """Least-squares Gates-Gaudin-Schuhmann fit ``P = 100 (x/k)^m`` (capped at 100).

        Fitted to the points strictly between 0 and 100 % passing, residuals
        in % passing.
        """
        from scipy.optimize import least_squares

        x, p = self._fit_points()
        lx = np.log(x)
        m0, c0 = np.polyfit(lx, np.log(p / 100.0), 1)
        m0 = max(float(m0), 0.05)
        k0 = float(np.exp(-c0 / m0))

        def resid(theta: NDArray[np.float64]) -> NDArray[np.float64]:
            lk, ln_m = theta
            m = np.exp(ln_m)
            return 100.0 * np.exp(np.minimum(m * (lx - lk), 0.0)) - p

        sol = least_squares(resid, [math.log(k0), math.log(m0)], method="trf")
        k, m = float(np.exp(sol.x[0])), float(np.exp(sol.x[1]))
        return _fit_result("gates_gaudin_schuhmann", {"k_mm": k, "m": m}, sol.fun, p)

    # ------------------------------------------------------------- dunders
    def __eq__(self, other: object) -> bool:
        if not isinstance(other, PSD):
            return NotImplemented
        return self._grid == other._grid and bool(np.array_equal(self._fractions, other._fractions))

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"PSD({self._grid!r}, P50={self.p50_mm:.4g} mm, P80={self.p80_mm:.4g} mm)"


def _fit_result(
    model: str, params: dict[str, float], resid: NDArray[np.float64], p: NDArray[np.float64]
) -> FitResult:
    ss_res = float(np.sum(resid**2))
    ss_tot = float(np.sum((p - p.mean()) ** 2))
    r2 = 1.0 - ss_res / ss_tot if ss_tot > 0 else float("nan")
    rmse = math.sqrt(ss_res / p.size)
    return FitResult(model=model, params=params, r_squared=r2, rmse_pct=rmse, n_points=int(p.size))


def ks_statistic(a: PSD, b: PSD) -> float:
    """Two-sample Kolmogorov-Smirnov statistic between two PSDs (domain notes §8).

    The largest absolute difference between the two cumulative mass-passing
    curves, both read (log-size interpolation, :meth:`PSD.passing_at`) on the
    union of their sieve sizes (``edges_mm[1:]`` of each grid).

    Parameters
    ----------
    a, b : PSD
        The two distributions (any grids).

    Returns
    -------
    float
        The statistic as a fraction in [0, 1].
    """
    for name, v in (("a", a), ("b", b)):
        if not isinstance(v, PSD):
            raise MsmillInputError(name, type(v).__name__, "a msmill.psd.PSD")
    sizes = np.union1d(a.sizes_mm, b.sizes_mm)
    d = np.abs(np.asarray(a.passing_at(sizes)) - np.asarray(b.passing_at(sizes)))
    return float(np.clip(d.max() / 100.0, 0.0, 1.0))
