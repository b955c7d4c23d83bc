"""Gaussian-process regression of many targets over the design space (scikit-learn).

One :class:`sklearn.gaussian_process.GaussianProcessRegressor` per target
(several outputs in one GPR would share one set of hyperparameters), all with
the paper's kernel::

    C1 * Matern(ARD, nu=3/2) + C2 * Matern(ARD, nu=5/2) + White

on inputs scaled to the unit cube by the design-space bounds (rock size in
``ln``) and outputs standardised (zero mean, unit variance over the training
runs). Each training point's sampling variance enters as per-point noise
(``alpha``, in standardised units); the white kernel adds what the sampling
errors do not explain. Fits run single-threaded (BLAS threads cost far more
than they gain on matrices this small) and can be warm-started from a
previous fit's hyperparameters.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
from scipy.linalg import cho_solve

from msmill.errors import MsmillInputError
from msmill.surrogate.space import DesignSpace
from msmill.threadpools import single_threaded

#: Bounds of the (unit-cube) ARD length scales, the signal variances and the white level.
LENGTH_SCALE_BOUNDS = (5e-2, 1e2)
CONSTANT_BOUNDS = (1e-3, 1e2)
WHITE_BOUNDS = (1e-6, 1.0)
#: Jitter added to every point's noise (standardised units) for a stable Cholesky.
JITTER = 1e-8


def make_kernel(params: dict[str, Any] | None = None) -> Any:
    """The paper's kernel; ``params`` (from :meth:`SurrogateGP.hyperparameters`) fixes its values."""
    from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel

    p = params or {"c32": 1.0, "ls32": [0.5] * 4, "c52": 1.0, "ls52": [0.5] * 4, "white": 1e-2}
    return (ConstantKernel(p["c32"], CONSTANT_BOUNDS) * Matern(np.array(p["ls32"], float), LENGTH_SCALE_BOUNDS, nu=1.5)
            + ConstantKernel(p["c52"], CONSTANT_BOUNDS) * Matern(np.array(p["ls52"], float), LENGTH_SCALE_BOUNDS, nu=2.5)
            + WhiteKernel(p["white"], WHITE_BOUNDS))


def kernel_params(kernel: Any) -> dict[str, Any]:
    """The fitted values of a :func:`make_kernel` kernel, as plain floats."""
    (a, b), w = (kernel.k1.k1, kernel.k1.k2), kernel.k2
    return {"c32": float(a.k1.constant_value), "ls32": [float(v) for v in np.atleast_1d(a.k2.length_scale)],
            "c52": float(b.k1.constant_value), "ls52": [float(v) for v in np.atleast_1d(b.k2.length_scale)],
            "white": float(w.noise_level)}


def _refactor(gpr: Any, params: dict[str, Any]) -> None:
    """Set a fitted GPR's kernel to exactly ``params`` and redo its final factorisation.

    scikit-learn's ``fit`` without an optimiser passes the kernel through
    ``theta = log(params)`` and back, which can move a value by one ulp; the
    original fit's final step used the optimiser's values directly. Redoing
    that step (the same operations as ``GaussianProcessRegressor.fit``) with
    the stored values gives bit-for-bit the original factorisation.
    """
    from scipy.linalg import cholesky

    gpr.kernel_ = make_kernel(params)
    K = gpr.kernel_(gpr.X_train_)
    K[np.diag_indices_from(K)] += gpr.alpha
    gpr.L_ = cholesky(K, lower=True, check_finite=False)
    gpr.alpha_ = cho_solve((gpr.L_, True), gpr.y_train_, check_finite=False)


class SurrogateGP:
    """Independent GPs, one per target column, scikit-learn style.

    Parameters
    ----------
    design_space : DesignSpace, optional
        Input bounds used for scaling (default paper Table 2).
    n_restarts : int
        Optimiser restarts from random hyperparameters (on top of the start).
    optimize : bool
        False keeps the start hyperparameters (``warm_start`` or the defaults).
    warm_start : list of dict, optional
        Start hyperparameters per target (e.g. the previous fit's
        :meth:`hyperparameters`).
    random_state : int
        Seed of the restarts.

    Attributes (after :meth:`fit`)
    ------------------------------
    estimators_ : list of GaussianProcessRegressor
    X_train_, Y_train_, noise_var_ : ndarray
        Training data in physical units (noise: sampling variances, target units).
    y_mean_, y_std_ : ndarray
        Standardisation of every target.
    white_ : ndarray
        Fitted white-noise level per target (standardised units).
    """

    def __init__(self, design_space: DesignSpace | None = None, n_restarts: int = 2, optimize: bool = True,
                 warm_start: list[dict[str, Any]] | None = None, random_state: int = 0) -> None:
        self.design_space = design_space or DesignSpace()
        self.n_restarts = n_restarts
        self.optimize = optimize
        self.warm_start = warm_start
        self.random_state = random_state

    # ------------------------------------------------------------------ fitting
    def fit(self, X: np.ndarray, Y: np.ndarray, noise_var: np.ndarray | None = None) -> SurrogateGP:
        """Fit one GP per column of ``Y`` (R, T) at design points ``X`` (R, 4); returns ``self``."""
        from sklearn.gaussian_process import GaussianProcessRegressor

        X, Y = np.asarray(X, dtype=float), np.atleast_2d(np.asarray(Y, dtype=float))
        if Y.shape[0] != X.shape[0]:
            Y = Y.T if Y.shape[1] == X.shape[0] else Y
        if Y.shape[0] != X.shape[0] or X.shape[0] < 2:
            raise MsmillInputError("Y", f"shape {Y.shape}", f"({X.shape[0]}, n_targets) with >= 2 runs")
        nv = np.zeros_like(Y) if noise_var is None else np.broadcast_to(np.asarray(noise_var, float), Y.shape)
        if not (np.all(np.isfinite(Y)) and np.all(np.isfinite(nv)) and np.all(nv >= 0)):
            raise MsmillInputError("targets", "non-finite or negative noise", "finite targets, noise >= 0")
        self.X_train_, self.Y_train_, self.noise_var_ = X.copy(), Y.copy(), np.array(nv, dtype=float)
        self.y_mean_, self.y_std_ = _standardisation(Y)
        U = self.design_space.to_unit(X)
        starts = self.warm_start or [None] * Y.shape[1]
        self.estimators_ = []
        with single_threaded(), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # convergence chatter at bounds on tiny data sets
            for j in range(Y.shape[1]):
                gpr = GaussianProcessRegressor(
                    kernel=make_kernel(starts[j]), alpha=self._alpha(j),
                    optimizer="fmin_l_bfgs_b" if self.optimize else None,
                    n_restarts_optimizer=self.n_restarts if self.optimize else 0,
                    normalize_y=False, copy_X_train=True, random_state=self.random_state)
                gpr.fit(U, (Y[:, j] - self.y_mean_[j]) / self.y_std_[j])
                self.estimators_.append(gpr)
        self.white_ = np.array([e.kernel_.k2.noise_level for e in self.estimators_])
        return self

    def _alpha(self, j: int) -> np.ndarray:
        return self.noise_var_[:, j] / self.y_std_[j] ** 2 + JITTER

    @property
    def estimators_(self) -> list[Any]:
        """The fitted scikit-learn GPRs; a GP loaded from its factors (:meth:`from_factors`) rebuilds
        them on first use (refits, leave-one-out, acquisition), predictions never need them."""
        if "_estimators" not in self.__dict__:  # unfitted (scikit-learn style: no fitted attribute)
            raise AttributeError("estimators_")
        ests = self.__dict__["_estimators"]
        if ests is None:
            ests = SurrogateGP.rebuild(self.X_train_, self.Y_train_, self.noise_var_, self._hyper,
                                       self.design_space).estimators_
            self.__dict__["_estimators"] = ests
            st = self.__dict__.get("_stacked_cache")
            if st is not None:
                st.source = ests  # the same fit: the stored factors stay valid
        return ests

    @estimators_.setter
    def estimators_(self, value: list[Any]) -> None:
        self.__dict__["_estimators"] = value

    @property
    def n_targets(self) -> int:
        """Number of target columns."""
        return len(self._hyper) if self.__dict__.get("_estimators") is None else len(self.estimators_)

    def hyperparameters(self) -> list[dict[str, Any]]:
        """Fitted kernel values per target (plain floats; see :func:`make_kernel`)."""
        if self.__dict__.get("_estimators") is None:
            return [dict(h) for h in self._hyper]
        return [kernel_params(e.kernel_) for e in self.estimators_]

    def factors(self) -> dict[str, np.ndarray]:
        """What prediction needs beyond the stored data and hyperparameters (:meth:`from_factors`):
        every target's dual coefficients ``alpha`` (T, R) and inverse Cholesky factor ``L_inv`` (T, R, R)."""
        st = self._stacked()
        return {"alpha": st.alpha, "L_inv": st.L_inv}

    @classmethod
    def from_factors(cls, X, Y, noise_var, hyperparameters, factors: dict[str, np.ndarray],
                     design_space: DesignSpace | None = None) -> SurrogateGP:
        """A fitted instance from stored data, hyperparameters and :meth:`factors`, without scikit-learn.

        Bit for bit the :meth:`rebuild` of the same data when ``factors`` came from it (they are its
        numbers); the estimators are rebuilt only if something asks for them.
        """
        gp = cls(design_space, optimize=False, warm_start=list(hyperparameters))
        X, Y = np.asarray(X, dtype=float), np.atleast_2d(np.asarray(Y, dtype=float))
        gp.X_train_, gp.Y_train_ = X.copy(), Y.copy()
        gp.noise_var_ = np.array(np.broadcast_to(np.asarray(noise_var, float), Y.shape), dtype=float)
        gp.y_mean_, gp.y_std_ = _standardisation(Y)
        gp.__dict__["_hyper"] = [dict(h) for h in hyperparameters]
        gp.__dict__["_estimators"] = None
        gp.white_ = np.array([float(h["white"]) for h in hyperparameters])
        arrays = {**_kernel_arrays(gp._hyper), "white": gp.white_, "alpha": np.asarray(factors["alpha"], dtype=float),
                  "L_inv": np.asarray(factors["L_inv"], dtype=float), "y_mean": gp.y_mean_, "y_std": gp.y_std_}
        n_t, n_r = Y.shape[1], X.shape[0]
        if arrays["alpha"].shape != (n_t, n_r) or arrays["L_inv"].shape != (n_t, n_r, n_r):
            raise MsmillInputError("factors", f"alpha {arrays['alpha'].shape}, L_inv {arrays['L_inv'].shape}",
                                   f"({n_t}, {n_r}) and ({n_t}, {n_r}, {n_r})")
        gp.__dict__["_stacked_cache"] = _Stacked(None, gp.design_space.to_unit(X), **arrays)
        return gp

    @classmethod
    def rebuild(cls, X, Y, noise_var, hyperparameters, design_space: DesignSpace | None = None) -> SurrogateGP:
        """A fitted instance from stored data and hyperparameters, without optimising."""
        gp = cls(design_space, optimize=False, warm_start=list(hyperparameters))
        gp.fit(X, Y, noise_var)
        for e, h in zip(gp.estimators_, hyperparameters, strict=True):
            _refactor(e, h)
        gp.white_ = np.array([e.kernel_.k2.noise_level for e in gp.estimators_])
        return gp

    # ------------------------------------------------------------------ predicting
    def _outputs(self, outputs) -> np.ndarray:
        return np.arange(self.n_targets) if outputs is None else np.asarray(outputs, dtype=int)

    def predict(self, X: np.ndarray, return_std: bool = False, outputs=None, include_noise: bool = False):
        """Posterior mean (and std) of the targets at ``X`` (P, 4), in target units.

        All targets at once (:class:`_Stacked`: the fitted GPs' kernels and
        factors as arrays); equal to the estimators' own ``predict`` to rounding.

        Parameters
        ----------
        X : ndarray (P, 4)
            Physical design points.
        return_std : bool
            Also return the standard deviation.
        outputs : sequence of int, optional
            Target columns to predict (default all).
        include_noise : bool
            Include the fitted white noise in the std (the scatter of a new DEM
            run); default False: the uncertainty of the mean.

        Returns
        -------
        mean : ndarray (P, T)
        std : ndarray (P, T), if ``return_std``
        """
        U = self.design_space.to_unit(np.atleast_2d(X))
        idx = self._outputs(outputs)
        st = self._stacked().take(idx, factor=return_std)
        with single_threaded():
            Kt = st.cross(U)  # (T, P, R)
            mean = np.einsum("tpr,tr->pt", Kt, st.alpha) * st.y_std + st.y_mean
            if not return_std:
                return mean
            V = st.L_inv @ np.swapaxes(Kt, 1, 2)  # (T, R, P)
            var = st.prior_var[:, None] - np.einsum("trp,trp->tp", V, V)
            if include_noise:
                var = var + st.white[:, None]
            std = np.sqrt(np.maximum(var, 0.0)).T * st.y_std
        return mean, std

    def spread_ratio(self, X: np.ndarray) -> np.ndarray:
        """Posterior sd of the mean over the prior sd at ``X`` (P, 4), the median over targets: (P,).

        Near a training run it is small (the run pins the mean down to its noise); far from every
        run it approaches 1 (the GP knows only its prior there).
        """
        _mean, std = self.predict(X, return_std=True)
        st = self._stacked()
        return np.median(std / (np.sqrt(st.prior_var) * st.y_std)[None, :], axis=1)

    def loo_spread_ratio(self) -> np.ndarray:
        """:meth:`spread_ratio` at every training run with that run left out (closed form): (R,).

        The leave-one-out predictive variance including the run's noise is ``1 / [K^-1]_ii``; less
        the noise (the sampling variance, the fitted white noise and the jitter) it is the latent
        variance the other runs leave at the run's point.
        """
        st = self._stacked()
        kinv_diag = np.einsum("tri,tri->ti", st.L_inv, st.L_inv)  # diag of K^-1 = L^-T L^-1, (T, R)
        noise = (self.noise_var_ / self.y_std_**2).T + JITTER + st.white[:, None]
        var = np.maximum(1.0 / kinv_diag - noise, 0.0)
        return np.median(np.sqrt(var / st.prior_var[:, None]), axis=0)

    def sample(self, X: np.ndarray, n_samples: int, outputs=None, rng=None) -> np.ndarray:
        """Joint posterior samples of the latent targets over the points ``X``.

        All targets at once (one batched eigendecomposition of the posterior
        covariances, :func:`sqrt_factor`); the normal deviates are drawn target by target in the
        order of ``outputs`` (``(n_samples, P)`` each), as one draw per target
        would.

        Returns
        -------
        ndarray (n_samples, P, T)
            Independent across targets, jointly Gaussian across points.
        """
        rng = np.random.default_rng(rng)
        U = self.design_space.to_unit(np.atleast_2d(X))
        idx = self._outputs(outputs)
        st = self._stacked().take(idx)
        with single_threaded():
            Kt = st.cross(U)  # (T, P, R)
            mean = np.einsum("tpr,tr->tp", Kt, st.alpha)
            V = st.L_inv @ np.swapaxes(Kt, 1, 2)  # (T, R, P)
            cov = st.latent(U, U) - np.swapaxes(V, 1, 2) @ V
            a = sqrt_factor(cov)
            z = rng.standard_normal((idx.size, n_samples, U.shape[0]))
            draws = mean[:, None, :] + z @ np.swapaxes(a, 1, 2)  # (T, n_samples, P)
        return np.transpose(draws, (1, 2, 0)) * st.y_std + st.y_mean

    def _stacked(self) -> _Stacked:
        """The fitted estimators as arrays (made once per fit)."""
        st = self.__dict__.get("_stacked_cache")
        if st is None or st.source is not self.__dict__.get("_estimators"):
            st = _Stacked.of(self)
            self.__dict__["_stacked_cache"] = st
        return st

    def loo(self) -> tuple[np.ndarray, np.ndarray]:
        """Closed-form leave-one-out mean and variance at the training points (target units).

        Rasmussen & Williams (2006) eq. 5.12 with the fitted hyperparameters
        (slightly optimistic: they saw the held-out point). The variance
        includes the point's noise.

        Returns
        -------
        mean, var : ndarray (R, T)
        """
        st = self._stacked()  # every target at once, from the stored factors (no scikit-learn refit)
        with single_threaded():
            kinv = np.swapaxes(st.L_inv, 1, 2) @ st.L_inv  # K^-1 = L^-T L^-1, (T, R, R)
            d = np.einsum("tii->ti", kinv)
            y = ((self.Y_train_ - self.y_mean_) / self.y_std_).T  # the standardised targets the GPs were fitted to
            mean = (y - np.einsum("tij,tj->ti", kinv, y) / d) * st.y_std[:, None] + st.y_mean[:, None]
            var = st.y_std[:, None] ** 2 / d
        return mean.T, var.T


def sqrt_factor(cov: np.ndarray) -> np.ndarray:
    """``A`` with ``A A^T = cov`` for (stacks of) covariance matrices (..., P, P): ``V sqrt(max(w, 0))``.

    ``V`` are the eigenvectors of the symmetrised ``cov``, each signed so that
    its dot product with a fixed irregular positive vector ``g`` is positive.
    The sign convention makes the factor (and so a posterior draw from given
    normal deviates) a continuous function of ``cov``: LAPACK's own signs can
    flip under a change in the last bit of ``cov``, which would turn rounding
    differences into a different draw. (A "largest component positive" rule
    is not enough: the eigenvectors over a regular size grid are often
    symmetric or antisymmetric, with two largest components of equal size.)
    """
    w, v = np.linalg.eigh(0.5 * (cov + np.swapaxes(cov, -1, -2)))
    g = 2.0 + np.cos(np.sqrt(2.0) * np.arange(v.shape[-1]) + 0.5)
    v = v * np.where(np.einsum("p,...pk->...k", g, v) < 0.0, -1.0, 1.0)[..., None, :]
    return v * np.sqrt(np.maximum(w, 0.0))[..., None, :]


def _matern(d: np.ndarray, nu: float) -> np.ndarray:
    """Matern correlation of scaled distances ``d`` (scikit-learn's formulas for nu = 3/2, 5/2), computed in
    place in ``d`` (which it returns): no temporaries but one, the same operations in the same order as
    ``(1 + k + k**2 / 3) * exp(-k)`` (bitwise equal; 1.7x faster on the stacked kernels of a prediction)."""
    k = d
    k *= np.sqrt(3.0) if nu == 1.5 else np.sqrt(5.0)
    sq = None if nu == 1.5 else np.square(k) / 3.0
    e = np.negative(k)
    np.exp(e, out=e)
    k += 1.0
    if sq is not None:
        k += sq
    k *= e
    return k


def _standardisation(Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation (1 where constant) that standardise every target column of ``Y``."""
    std = Y.std(axis=0)
    return Y.mean(axis=0), np.where(std > 1e-12, std, 1.0)


def _kernel_arrays(hyperparameters: list[dict[str, Any]]) -> dict[str, np.ndarray]:
    """The kernel values of every target (:func:`kernel_params` dicts) as arrays over targets."""
    hp = hyperparameters
    return {"c32": np.array([h["c32"] for h in hp]), "c52": np.array([h["c52"] for h in hp]),
            "ls32": np.array([np.broadcast_to(h["ls32"], (4,)) for h in hp]),
            "ls52": np.array([np.broadcast_to(h["ls52"], (4,)) for h in hp])}


class _Stacked:
    """Kernel hyperparameters and factors of every fitted GP as arrays over targets (first axis).

    ``alpha`` and ``L_inv`` (the inverse of each Cholesky factor, for the
    predictive variance) come from the estimators' own factorisation.
    """

    FIELDS = ("c32", "ls32", "c52", "ls52", "white", "alpha", "L_inv", "y_mean", "y_std")

    def __init__(self, source: Any, X_train: np.ndarray, **arrays: np.ndarray) -> None:
        self.source = source
        self.X_train = X_train
        for k in self.FIELDS:
            setattr(self, k, arrays[k])
        self.prior_var = self.c32 + self.c52

    @classmethod
    def of(cls, gp: SurrogateGP) -> _Stacked:
        from scipy.linalg import solve_triangular

        hp = gp.hyperparameters()
        ests = gp.estimators_
        eye = np.eye(ests[0].X_train_.shape[0])
        arrays = {
            **_kernel_arrays(hp), "white": np.asarray(gp.white_, dtype=float), "alpha": np.array([e.alpha_ for e in ests]),
            "L_inv": np.array([solve_triangular(e.L_, eye, lower=True) for e in ests]),
            "y_mean": np.asarray(gp.y_mean_, dtype=float), "y_std": np.asarray(gp.y_std_, dtype=float)}
        return cls(ests, ests[0].X_train_, **arrays)

    def take(self, idx: np.ndarray, factor: bool = True) -> _Stacked:
        """The targets ``idx`` only (this stack itself when ``idx`` is all of them, in order).

        ``factor=False`` leaves out ``L_inv`` (None), the one large array (T, R, R), for a posterior mean.
        """
        if len(idx) == len(self.alpha) and np.array_equal(idx, np.arange(len(self.alpha))):
            return self
        return _Stacked(self.source, self.X_train, **{k: None if k == "L_inv" and not factor else getattr(self, k)[idx]
                                                     for k in self.FIELDS})

    def latent(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        """Latent (noise-free) kernel between unit-cube points ``A`` (P, 4) and ``B`` (Q, 4): (T, P, Q)."""
        out = None
        for c, ls, nu in ((self.c32, self.ls32, 1.5), (self.c52, self.ls52, 2.5)):
            a, b = A[None] / ls[:, None, :], B[None] / ls[:, None, :]
            # |a - b|^2 = |a|^2 + |b|^2 - 2 a.b: batched products instead of a (T, P, Q, 4) difference
            # (3x faster; equal to 1e-15 relative; a distance's rounding near 0 moves the Matern
            # correlation, flat there, by about its square)
            d2 = np.einsum("tpk,tpk->tp", a, a)[:, :, None] + np.einsum("tqk,tqk->tq", b, b)[:, None, :]
            ab = a @ np.swapaxes(b, 1, 2)
            ab *= 2.0
            d2 -= ab
            np.maximum(d2, 0.0, out=d2)
            k = _matern(np.sqrt(d2, out=d2), nu)
            k *= c[:, None, None]
            if out is None:
                out = k
            else:
                out += k
        return out

    def cross(self, U: np.ndarray) -> np.ndarray:
        """Kernel between ``U`` (P, 4) and the training inputs: (T, P, R)."""
        return self.latent(U, self.X_train)
