"""Calibration of the breakage model (paper Eq. 11-12, Section 3.2.1) to drop-weight data.

The fitted model is the laboratory test simulated through the breakage
sub-model the mill model uses: one impact per rock at the tested size and
energy, and the t10 of the whole population (broken and unbroken rock). With
the t10 convention ``"jk"`` (default, :data:`msmill.breakage.T10_CONVENTIONS`)
that is the JK law ``t10 = A (1 - exp(-b E_cs L / L_ref))``; with ``"paper"``
(broken rock ``t10 = A P_b``) it is ``A P_b**2``. ``t10`` in %, ``E_cs`` in
kWh/t, ``L`` and ``L_ref`` in mm. Data: a table with columns ``size_mm``,
``ecs_kwh_t`` and ``t10_pct`` (one row per test or per size/energy mean).
A caller that has the sub-model itself may pass its simulated lab test as
``lab_test`` (``msmill.model.submodels.lab_test``).

Identifiability: ``b`` and ``L_ref`` enter only through ``b / L_ref``, so t10
data cannot determine both. :func:`calibrate` fits ``L_ref`` (default), or
``A`` and ``L_ref``, or ``A`` and ``b`` (with ``L_ref`` held), but refuses
``b`` together with ``L_ref``.

Standard errors come from the Jacobian at the optimum,
``cov = s² (JᵀJ)⁻¹`` with ``s² = SSR / (n - p)``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from msmill.breakage import T10_CONVENTIONS, population_t10_pct
from msmill.errors import MsmillInputError
from msmill.ore import DEFAULT_L_REF_MM, Ore

__all__ = [
    "FIT_PARAMETERS",
    "CalibrationResult",
    "calibrate",
    "read_dropweight_csv",
    "t10_model_pct",
    "validate_dropweight_frame",
]

#: Parameters that can be fitted.
FIT_PARAMETERS = ("A_pct", "b_t_per_kwh", "l_ref_mm")
_COLUMNS = ("size_mm", "ecs_kwh_t", "t10_pct")


def t10_model_pct(
    size_mm: NDArray[np.float64] | float,
    ecs_kwh_t: NDArray[np.float64] | float,
    A_pct: float,
    b_t_per_kwh: float,
    l_ref_mm: float,
) -> NDArray[np.float64]:
    """``t10 = A (1 - exp(-b E L / L_ref))`` (%), vectorised, no validation (fitting kernel)."""
    x = b_t_per_kwh * np.asarray(ecs_kwh_t) * np.asarray(size_mm) / l_ref_mm
    return A_pct * -np.expm1(-x)


#: Plausibility bounds of drop-weight data: drop-weight and JK rotary breakage tests span
#: about 0.01-5 kWh/t on 10-100 mm rocks; beyond these a row is a unit or typing error.
MAX_ECS_KWH_T = 100.0
MAX_SIZE_MM = 1000.0


def validate_dropweight_frame(frame: pd.DataFrame, origin: str = "data") -> pd.DataFrame:
    """Check a drop-weight table and return it with float columns ``size_mm, ecs_kwh_t, t10_pct``.

    Raises
    ------
    MsmillInputError
        Missing columns, non-numbers, sizes <= 0, energies < 0, t10 outside
        0-100 %, or fewer than 2 rows; the message names the column and row.
    """
    if not isinstance(frame, pd.DataFrame):
        raise MsmillInputError(origin, type(frame).__name__, "a pandas DataFrame")
    cols = [str(c).strip() for c in frame.columns]
    frame = frame.set_axis(cols, axis=1)
    missing = [c for c in _COLUMNS if c not in cols]
    if missing:
        raise MsmillInputError(f"{origin}.columns", cols, f"columns {', '.join(_COLUMNS)}")
    df = frame[list(_COLUMNS)].copy()
    for col in _COLUMNS:
        vals = pd.to_numeric(df[col], errors="coerce")
        bad = vals.isna() | ~np.isfinite(vals.to_numpy(dtype=float, na_value=np.nan))
        if bad.any():
            i = int(np.flatnonzero(bad.to_numpy())[0])
            raise MsmillInputError(f"{origin}.{col}[row {i + 1}]", df[col].iloc[i], "a finite number")
        df[col] = vals.astype(float)
    checks = (
        ("size_mm", (df["size_mm"] <= 0) | (df["size_mm"] > MAX_SIZE_MM), f"a size in (0, {MAX_SIZE_MM:g}] mm"),
        ("ecs_kwh_t", (df["ecs_kwh_t"] < 0) | (df["ecs_kwh_t"] > MAX_ECS_KWH_T),
         f"a specific energy in [0, {MAX_ECS_KWH_T:g}] kWh/t"),
        ("t10_pct", (df["t10_pct"] < 0) | (df["t10_pct"] > 100), "t10 within 0-100 %"),
    )
    for col, mask, allowed in checks:
        if mask.any():
            i = int(np.flatnonzero(mask.to_numpy())[0])
            raise MsmillInputError(f"{origin}.{col}[row {i + 1}]", float(df[col].iloc[i]), allowed)
    if len(df) < 2:
        raise MsmillInputError(f"{origin}.rows", len(df), "at least 2 data rows")
    for col in ("t10_pct", "ecs_kwh_t"):
        v = df[col].to_numpy()
        if np.ptp(v) == 0:
            raise MsmillInputError(f"{origin}.{col}", f"{v[0]:g} in every row",
                                   "values that vary between rows (a constant column has nothing to fit)")
    if not (df["t10_pct"] > 0).any():
        raise MsmillInputError(f"{origin}.t10_pct", "0 in every row", "some rows with t10 > 0 %")
    return df.reset_index(drop=True)


def read_dropweight_csv(path: str | Path) -> pd.DataFrame:
    """Read and validate a drop-weight CSV (``#`` lines are comments)."""
    from msmill.validate import read_csv

    p = Path(path)
    return validate_dropweight_frame(read_csv(p, "path", "drop-weight CSV file"), origin=p.name)


@dataclass(frozen=True)
class CalibrationResult:
    """Result of :func:`calibrate`.

    Attributes
    ----------
    params : dict[str, float]
        ``A_pct`` (%), ``b_t_per_kwh`` (t/kWh), ``l_ref_mm`` (mm): fitted or held.
    fitted : tuple[str, ...]
        Names of the fitted parameters.
    std_errors : dict[str, float]
        One-sigma standard errors of the fitted parameters (same units).
    r_squared : float
        Coefficient of determination of t10.
    rmse_pct : float
        Root-mean-square residual of t10 (%).
    n_points : int
        Number of data rows.
    residuals : pandas.DataFrame
        ``size_mm, ecs_kwh_t, t10_pct, t10_fit_pct, residual_pct``.
    success : bool
        Whether the optimiser reported convergence.
    message : str
        Optimiser message.
    """

    params: dict[str, float]
    fitted: tuple[str, ...]
    std_errors: dict[str, float]
    r_squared: float
    rmse_pct: float
    n_points: int
    residuals: pd.DataFrame = field(repr=False)
    success: bool = True
    message: str = ""
    convention: str = "jk"

    def to_ore(self, ore: Ore, source: str = "") -> Ore:
        """Copy of ``ore`` with the calibrated parameters and provenance."""
        note = source or (
            f"msmill calibration: fitted {', '.join(self.fitted)}; "
            + ", ".join(f"{k} = {self.params[k]:.4g} +- {self.std_errors[k]:.2g}" for k in self.fitted)
            + f"; R^2 = {self.r_squared:.4f}, n = {self.n_points}; t10 convention {self.convention!r}"
        )
        new = ore.with_l_ref(self.params["l_ref_mm"], note)
        upd: dict[str, object] = {}
        if "A_pct" in self.fitted or "b_t_per_kwh" in self.fitted:
            upd = {"A_pct": self.params["A_pct"], "b_t_per_kwh": self.params["b_t_per_kwh"]}
            srcs = dict(new.sources)
            srcs["breakage"] = note
            upd["sources"] = srcs
        return new.model_copy(update=upd) if upd else new


def calibrate(
    data: pd.DataFrame | str | Path,
    ore: Ore | None = None,
    *,
    fit: Sequence[str] = ("l_ref_mm",),
    A_pct: float | None = None,
    b_t_per_kwh: float | None = None,
    l_ref_mm: float | None = None,
    convention: str = "jk",
    lab_test: Callable[..., NDArray[np.float64]] | None = None,
) -> CalibrationResult:
    """Fit Eq. 11-12, read in a t10 convention, to drop-weight data by nonlinear least squares.

    Parameters
    ----------
    data : DataFrame or path
        Table with ``size_mm``, ``ecs_kwh_t`` (kWh/t), ``t10_pct`` (%).
    ore : Ore, optional
        Supplies held parameters and start values.
    fit : sequence of str, optional
        Parameters to fit, from ``A_pct``, ``b_t_per_kwh``, ``l_ref_mm``
        (not ``b_t_per_kwh`` together with ``l_ref_mm``). Default: ``L_ref`` only.
    A_pct, b_t_per_kwh, l_ref_mm : float, optional
        Held values / start values overriding the ore's.
    convention : {"jk", "paper"}
        t10 convention of the breakage sub-model the parameters are for
        (:func:`msmill.breakage.population_t10_pct`).
    lab_test : callable, optional
        ``lab_test(size_mm, ecs_kwh_t, A_pct, b_t_per_kwh, l_ref_mm) -> t10_pct``: the population
        t10 of the simulated laboratory test; overrides ``convention``.

    Returns
    -------
    CalibrationResult
    """
    from scipy.optimize import least_squares

    if convention not in T10_CONVENTIONS:
        raise MsmillInputError("convention", convention, "one of " + ", ".join(map(repr, T10_CONVENTIONS)))
    df = validate_dropweight_frame(data) if isinstance(data, pd.DataFrame) else read_dropweight_csv(data)
    fit = tuple(dict.fromkeys(fit))
    if not fit or any(f not in FIT_PARAMETERS for f in fit):
        raise MsmillInputError("fit", list(fit), f"a non-empty subset of {', '.join(FIT_PARAMETERS)}")
    if "b_t_per_kwh" in fit and "l_ref_mm" in fit:
        raise MsmillInputError(
            "fit", list(fit), "not both b_t_per_kwh and l_ref_mm (they enter Eq. 11 only as b/L_ref)"
        )
    values = {
        "A_pct": A_pct if A_pct is not None else (ore.A_pct if ore else None),
        "b_t_per_kwh": b_t_per_kwh if b_t_per_kwh is not None else (ore.b_t_per_kwh if ore else None),
        "l_ref_mm": l_ref_mm if l_ref_mm is not None else (ore.l_ref_mm if ore else DEFAULT_L_REF_MM),
    }
    t10 = df["t10_pct"].to_numpy()
    if values["A_pct"] is None and "A_pct" in fit:
        values["A_pct"] = float(min(100.0, max(1.0, 1.1 * t10.max())))
    if values["b_t_per_kwh"] is None and "b_t_per_kwh" in fit:
        values["b_t_per_kwh"] = 1.0
    for name, v in values.items():
        if v is None:
            raise MsmillInputError(name, None, "a value (give an ore or the parameter) when it is not fitted")
        if not (math.isfinite(float(v)) and float(v) > 0) or (name == "A_pct" and float(v) > 100):
            raise MsmillInputError(name, v, "A in (0, 100] %" if name == "A_pct" else "a number > 0")
    n, p = len(df), len(fit)
    if n <= p:
        raise MsmillInputError("data.rows", n, f"more than {p} rows to fit {p} parameter(s)")

    size = df["size_mm"].to_numpy()
    ecs = df["ecs_kwh_t"].to_numpy()
    x0 = np.array([float(values[f]) for f in fit])
    lo = np.array([1e-9] * p)
    hi = np.array([100.0 if f == "A_pct" else np.inf for f in fit])
    x0 = np.clip(x0, lo * 10, np.where(np.isfinite(hi), hi, np.inf))

    def unpack(x: NDArray[np.float64]) -> dict[str, float]:
        d = {k: float(v) for k, v in values.items()}  # type: ignore[arg-type]
        d.update(dict(zip(fit, (float(v) for v in x), strict=True)))
        return d

    def model(p: dict[str, float]) -> NDArray[np.float64]:
        if lab_test is not None:
            return np.asarray(lab_test(size, ecs, **p), dtype=float)
        return np.asarray(population_t10_pct(ecs, size, p["A_pct"], p["b_t_per_kwh"], p["l_ref_mm"], convention))

    def resid(x: NDArray[np.float64]) -> NDArray[np.float64]:
        return model(unpack(x)) - t10

    sol = least_squares(resid, x0, bounds=(lo, hi), x_scale="jac", method="trf")
    params = unpack(sol.x)
    r = sol.fun
    ssr = float(r @ r)
    dof = n - p
    s2 = ssr / dof
    jtj = sol.jac.T @ sol.jac
    try:
        cov = np.linalg.inv(jtj) * s2
        se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    except np.linalg.LinAlgError:
        se = np.full(p, np.inf)
    ss_tot = float(np.sum((t10 - t10.mean()) ** 2))
    at_bound = bool(np.any(np.isclose(sol.x, lo, rtol=1e-6) | np.isclose(sol.x, hi, rtol=1e-6)))
    message = str(sol.message) + ("; a fitted parameter sits at its bound" if at_bound else "")
    fitted_vals = model(params)
    table = df.assign(t10_fit_pct=fitted_vals, residual_pct=t10 - fitted_vals)
    return CalibrationResult(
        params=params,
        fitted=fit,
        std_errors={f: float(s) for f, s in zip(fit, se, strict=True)},
        r_squared=1.0 - ssr / ss_tot if ss_tot > 0 else float("nan"),
        rmse_pct=math.sqrt(ssr / n),
        n_points=n,
        residuals=table,
        success=bool(sol.success) and not at_bound and bool(np.all(np.isfinite(se))),
        message=message,
        convention=getattr(lab_test, "convention", "custom lab test") if lab_test is not None else convention,
    )
