"""Expected-value solver: the mill as a linear system on (compartment, size, damage).

State
-----
``x[c, i, d]``: tonnes of rock in compartment ``c`` (0 = inlet zone, 1..S =
stages), size class ``i`` and damage class ``d``, flattened as
``c * (N * n_d) + i * n_d + d``. Damage classes are nodes
``D_d = d * D_th / n_d`` (``d = 0 .. n_d-1``); fresh rock and fragments are in
class 0.

One step (characteristic time) is ``x(t+1) = M x(t) + f`` and the product of
the step is ``out_op x(t)`` (see docs/model.md for the semantics). Every impact is a
linear operator averaged over the velocity distribution by Gauss-Hermite
quadrature per mixture component (velocities clipped at 0); a Poisson number of
secondary impacts is ``expm(lambda (T - I))`` on a state augmented with the
fragments made so far (which are not hit again in that step) and two counters
(number of impacts and energy delivered), and a Poisson-mixture number is the
weighted sum of those per-component operators (:func:`secondary_series`). The steady state solves
``(I - M) x = f`` directly (sparse LU).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from msmill.errors import MsmillError
from msmill.model.parameters import CountArrays, MixtureArrays
from msmill.model.submodels import (
    ImpactStatistics,
    as_transition,
    fragment_index,
    specific_energy_kwh_t,
)


def quadrature(mix: MixtureArrays, n_nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Hermite nodes and weights of a Gaussian mixture, per (..., size).

    Parameters
    ----------
    mix : MixtureArrays
        Arrays of shape (..., K).
    n_nodes : int
        Gauss-Hermite nodes per component.

    Returns
    -------
    v_m_s, weights : ndarray, shape (..., K * n_nodes)
        Velocities clipped at 0 (m/s) and weights (sum 1).
    """
    x, w = np.polynomial.hermite.hermgauss(n_nodes)
    v = mix.means_m_s[..., None] + np.sqrt(2.0) * mix.sigmas_m_s[..., None] * x
    ww = mix.weights[..., None] * (w / np.sqrt(np.pi))
    shape = (*v.shape[:-2], v.shape[-2] * v.shape[-1])
    v = np.maximum(v.reshape(shape), 0.0)
    ww = ww.reshape(shape)
    ww = ww / ww.sum(axis=-1, keepdims=True)
    return v, ww


@dataclass(frozen=True)
class ImpactOperator:
    """One impact on rocks of every (size, damage) class, averaged over velocity.

    Attributes
    ----------
    survive : ndarray (N, n_d, n_d)
        ``survive[i, d2, d]``: fraction of (i, d) that survives in damage class d2.
    fragments : ndarray (N, N, n_d)
        ``fragments[k, i, d]``: fraction of (i, d) that breaks into class k.
    mean_energy_kwh_t : ndarray (N,)
        Mean specific impact energy per impact (kWh/t).
    """

    survive: np.ndarray
    fragments: np.ndarray
    mean_energy_kwh_t: np.ndarray


def damage_nodes(n_classes: int, threshold: float) -> np.ndarray:
    """Damage class nodes ``D_d = d * threshold / n_classes`` (dimensionless)."""
    return np.arange(n_classes) * (threshold / n_classes)


def split_damage(d_new: np.ndarray, n_classes: int, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Lower class index and upper weight of a damage value (mass-conservative linear split).

    ``D`` between nodes ``D_lo`` and ``D_lo+1`` goes to them with weights
    ``1 - frac`` and ``frac``; ``D`` above the last node (but below the
    threshold) stays in the last class.
    """
    step = threshold / n_classes
    pos = np.asarray(d_new, dtype=float) / step
    lo = np.floor(pos).astype(int)
    frac = pos - lo
    top = lo >= n_classes - 1
    lo = np.clip(lo, 0, n_classes - 1)
    frac = np.where(top, 0.0, frac)
    return lo, frac


def impact_operator(edges_mm: np.ndarray, mix: MixtureArrays, breakage, damage, n_damage: int,
                    n_nodes: int) -> ImpactOperator:
    """Build the one-impact operator of one stage (mixture arrays of shape (N, K))."""
    m = MixtureArrays(*(np.asarray(a, dtype=float)[None] for a in (mix.weights, mix.means_m_s, mix.sigmas_m_s)))
    op = impact_operators(edges_mm, m, breakage, damage, n_damage, n_nodes)
    return ImpactOperator(op.survive[0], op.fragments[0], op.mean_energy_kwh_t[0])


#: Largest array (elements) :func:`impact_operators` makes at once; bigger batches go in chunks
#: (work arrays that stay in cache: one 2M-element chunk instead is 1.5x slower).
BATCH_ELEMENTS = 1 << 17


def impact_operators(edges_mm: np.ndarray, mix: MixtureArrays, breakage, damage, n_damage: int,
                     n_nodes: int) -> ImpactOperator:
    """One-impact operators of a batch of velocity distributions (mixture arrays (B, N, K)).

    The batch is folded into the damage axis of the sub-model calls (they are
    elementwise in energy, size and damage, and ``expected_fragments`` works
    column by column), so a batch costs about one stage's number of numpy calls.

    Returns
    -------
    ImpactOperator
        With a leading batch axis: ``survive`` (B, N, nd, nd), ``fragments``
        (B, N, N, nd), ``mean_energy_kwh_t`` (B, N).
    """
    v, w = quadrature(mix, n_nodes)  # (B, N, Q)
    b, n, q = v.shape
    per = n * q * n_damage * (1 if hasattr(breakage, "expected_fragments") else n)
    step = max(1, BATCH_ELEMENTS // per)
    parts = [_impact_chunk(edges_mm, v[i:i + step], w[i:i + step], breakage, damage, n_damage)
             for i in range(0, b, step)]
    return ImpactOperator(*(np.concatenate(a) for a in zip(*parts, strict=True)))


def _impact_chunk(edges_mm, v, w, breakage, damage, nd) -> tuple[np.ndarray, ...]:
    """:func:`impact_operators` of one chunk: velocities and weights (B, N, Q)."""
    b, n, q = v.shape
    mids = np.sqrt(edges_mm[:-1] * edges_mm[1:])
    th = float(damage.threshold)
    e = specific_energy_kwh_t(v)
    cols = b * nd  # folded (batch, damage) columns
    fold = lambda a: np.broadcast_to(np.moveaxis(a, 0, -1)[..., None], (n, q, b, nd)).reshape(n, q, cols)  # noqa: E731
    ef = fold(e)
    dn = np.tile(damage_nodes(nd, th), b)[None, None, :]
    L = mids[:, None, None]
    pb = breakage.probability(ef, L, dn)  # (N, Q, cols)
    d_new = damage.after_impact(ef, L, dn)
    broke_thr = d_new >= th
    pbr = pb + (1.0 - pb) * broke_thr
    wf = fold(w)
    u = fragment_index(breakage, ef, L, dn, pb)  # what sets the fragments (pb unless the sub-model says)
    if hasattr(breakage, "expected_fragments"):  # optional fast path of the sub-model
        frag = breakage.expected_fragments(edges_mm, u, wf * pbr)
    else:
        parent = np.broadcast_to(np.arange(n)[:, None, None], pb.shape)
        frag = np.einsum("iqd,iqdk->kid", wf * pbr, breakage.fragments(edges_mm, parent, u))
    surv = wf * (1.0 - pbr)  # (N, Q, cols)
    lo, frac = split_damage(np.where(broke_thr, 0.0, d_new), nd, th)
    # survivors of (i, column) land in damage classes lo and lo + 1 (frac = 0 at the top class)
    row = np.arange(n)[:, None, None] * nd
    col = np.arange(cols)[None, None, :]
    size = n * nd * cols
    S = (np.bincount(((row + lo) * cols + col).ravel(), (surv * (1.0 - frac)).ravel(), size)
         + np.bincount(((row + np.minimum(lo + 1, nd - 1)) * cols + col).ravel(), (surv * frac).ravel(), size))
    S = np.moveaxis(S.reshape(n, nd, b, nd), 2, 0)  # (B, N, nd2, nd)
    frag = np.moveaxis(frag.reshape(n, n, b, nd), 2, 0)  # (B, N_k, N_i, nd)
    return S, frag, np.sum(w * e, axis=-1)


@dataclass(frozen=True)
class StageOperator:
    """Everything one stage does to the mass it impacts in one step.

    Attributes
    ----------
    G : ndarray (n_s, n_s)
        Impacted mass -> mass after the step's impacts (columns sum to 1).
    primary_count, primary_energy_kwh_t, secondary_count, secondary_energy_kwh_t : ndarray (n_s,)
        Per tonne impacted: expected number of impacts and energy delivered (kWh/t).
    """

    G: np.ndarray
    primary_count: np.ndarray
    primary_energy_kwh_t: np.ndarray
    secondary_count: np.ndarray
    secondary_energy_kwh_t: np.ndarray


def _block_diag(blocks: np.ndarray) -> np.ndarray:
    n, m, _ = blocks.shape
    out = np.zeros((n * m, n * m))
    for i in range(n):
        out[i * m:(i + 1) * m, i * m:(i + 1) * m] = blocks[i]
    return out


#: Smallest and largest series length of a group of rows in :func:`secondary_series` ("auto");
#: a group needing more terms goes through expm.
SERIES_MIN_GROUP = 64
SERIES_MAX_GROUP = 256
_SERIES_TAIL = 1e-18  # P(K > k_max) and the neglected part of E[K] stay below this (per unit mass)


def secondary_series(survive: np.ndarray, weights: np.ndarray, means: np.ndarray,
                     method: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """Survivor operator and impact-weighted operator of a Poisson-mixture number of secondary impacts.

    With one-impact survivor block ``S_i`` (size class ``i``; survivors keep
    their size) and ``K ~ sum_c w_c Poisson(lam_c)`` impacts, the survivors of
    the impacts are ``E[S^K] = sum_k P(K = k) S^k`` and the mass impacted by the
    ``j``-th impact is ``P(K > j) S^j``, so the expected number of impacts
    applied to the mass is ``phi = sum_j P(K > j) S^j``. Two exact constructions:

    * ``"expm"``: per component ``A = lam_c (S - I)``, ``E[S^K] = e^A`` and
      ``phi = lam_c phi1(A)``, ``phi1(A) = int_0^1 e^(tA) dt``, both read off one
      batched ``expm`` of ``[[A, 0], [I, 0]]`` (``expm([[A, 0], [C, 0]]) =
      [[e^A, 0], [C phi1(A), I]]``); a mixture is the ``w_c``-weighted sum of
      the per-component operators (the step is linear in the count
      distribution) and a component of mean 0 contributes ``e^A = I``,
      ``phi = 0``. One ``expm`` per active (size class, component).
    * ``"series"``: the two sums above, to the ``k_max`` where ``P(K > k_max)``
      and ``sum_{j > k_max} P(K > j)`` are below 1e-18 (``S >= 0`` with
      column sums <= 1, so the neglected part of every column is below that:
      exact to rounding). All terms are non-negative, so there is no
      cancellation; the cost is ``k_max`` batched products, independent of
      the number of components.

    ``"auto"`` (default) groups the size classes (rows) by the ``k_max`` they
    need (powers of two from :data:`SERIES_MIN_GROUP`), so a large batch is
    not summed as far as its largest mean needs, and uses the series for a
    group up to :data:`SERIES_MAX_GROUP` terms, ``expm`` beyond (a few rows
    with large means: ``k_max`` products of a few matrices cost more than
    their ``expm``).

    Parameters
    ----------
    survive : ndarray (N, nd, nd)
        One-impact survivor blocks per size class.
    weights, means : ndarray (N, C)
        Count mixture per size class.
    method : {"auto", "series", "expm"}

    Returns
    -------
    eA, phi : ndarray (N, nd, nd)
        ``E[S^K]`` and ``sum_j P(K > j) S^j``.
    """
    w, lam = np.asarray(weights, dtype=float), np.asarray(means, dtype=float)
    if method not in ("auto", "series", "expm"):
        raise ValueError(method)
    if method == "expm":
        return _expm_series(survive, w, lam)
    if method == "series":
        return _series_or_expm(survive, w, lam, None)
    eA, phi = np.empty(survive.shape), np.empty(survive.shape)
    for rows in _series_groups(w, lam):
        eA[rows], phi[rows] = _series_or_expm(survive[rows], w[rows], lam[rows], SERIES_MAX_GROUP)
    return eA, phi



def _k_max(lam_max: np.ndarray) -> np.ndarray:
    """Series length for a largest Poisson mean ``lam_max`` (the mass beyond is below 1e-30)."""
    return (lam_max + 12.0 * np.sqrt(lam_max) + 40).astype(int)


def _series_groups(w: np.ndarray, lam: np.ndarray) -> list[np.ndarray]:
    """Rows grouped by the series length they need (powers of two from :data:`SERIES_MIN_GROUP`)."""
    k = _k_max(np.max(np.where(w > 0, lam, 0.0), axis=-1, initial=0.0))
    g = np.ceil(np.log2(np.maximum(k, SERIES_MIN_GROUP) / SERIES_MIN_GROUP)).astype(int)
    return [np.flatnonzero(g == v) for v in np.unique(g)]


def _series_or_expm(survive, w, lam, k_cap) -> tuple[np.ndarray, np.ndarray]:
    tails = _count_tails(w, lam, k_cap)
    return _power_series(survive, *tails) if tails is not None else _expm_series(survive, w, lam)


def _count_tails(w: np.ndarray, lam: np.ndarray, k_cap: int | None) -> tuple[np.ndarray, np.ndarray] | None:
    """``(P(K = k), P(K > k))`` for ``k = 0..k_max``, shape (N, k_max + 1); None beyond ``k_cap``."""
    from scipy import special

    lam_max = float(lam[w > 0].max()) if np.any(w > 0) else 0.0
    k_max = int(_k_max(np.array(lam_max)))  # Poisson mass beyond: < 1e-30
    if k_cap is not None and k_max > k_cap:
        return None
    k = np.arange(k_max + 2, dtype=float)
    lp = special.xlogy(k, lam[..., None]) - lam[..., None] - special.gammaln(k + 1.0)  # (N, C, k_max + 2)
    pk = np.einsum("nc,nck->nk", w, np.exp(lp))
    pk /= pk.sum(axis=1, keepdims=True)  # the weights' and the pmf's rounding: total mass exactly 1
    qk = np.cumsum(pk[:, ::-1], axis=1)[:, ::-1][:, 1:]  # P(K > k), summed from the tail: no cancellation
    if qk[:, -1].max() > _SERIES_TAIL:  # pragma: no cover - the bound above is generous
        return None
    return pk[:, :-1], qk


def _power_series(survive: np.ndarray, pk: np.ndarray, qk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``sum_k pk S^k`` and ``sum_k qk S^k`` per row, each row to its own length.

    A row stops after the first ``k`` where ``P(K > k)`` and ``sum_{j > k} P(K > j)``
    are both below the series tolerance (what it neglects of every column is
    below that); rows are sorted by length so each step multiplies only the
    rows still running (a prefix).
    """
    n, nd, _ = survive.shape
    tail_q = np.cumsum(qk[:, ::-1], axis=1)[:, ::-1] - qk  # sum_{j > k} P(K > j)
    done = (qk <= _SERIES_TAIL) & (tail_q <= _SERIES_TAIL)
    length = np.where(done.any(axis=1), np.argmax(done, axis=1), qk.shape[1] - 1) + 1  # terms per row
    order = np.argsort(-length, kind="stable")
    S, p, q = survive[order], pk[order], qk[order]
    running = np.searchsorted(-length[order], -np.arange(length.max()), side="right")  # rows still at term j
    power = np.broadcast_to(np.eye(nd), (n, nd, nd)).copy()
    eA = np.zeros((n, nd, nd))
    phi = np.zeros((n, nd, nd))
    for j, r in enumerate(running):  # loop over the impact number, batched over the running rows
        eA[:r] += p[:r, j, None, None] * power[:r]
        phi[:r] += q[:r, j, None, None] * power[:r]
        power[:r] = S[:r] @ power[:r]
    out_eA, out_phi = np.empty_like(eA), np.empty_like(phi)
    out_eA[order], out_phi[order] = eA, phi
    return out_eA, out_phi


#: Higham (2005) degree-13 Pade coefficients and the 1-norm up to which it is accurate to double precision
_PADE13 = (64764752532480000.0, 32382376266240000.0, 7771770303897600.0, 1187353796428800.0, 129060195264000.0,
           10559470521600.0, 670442572800.0, 33522128640.0, 1323241920.0, 40840800.0, 960960.0, 16380.0, 182.0,
           1.0)
_THETA13 = 5.371920351148152


def expm_batched(Z: np.ndarray) -> np.ndarray:
    """Matrix exponentials of a stack ``Z`` (n, m, m): scaling and squaring with the degree-13 Pade approximant
    (Higham 2005), every matrix at once.

    ``scipy.linalg.expm`` takes a stack but treats it matrix by matrix in Python (about 0.03 ms each, hundreds
    per prediction); here each matrix gets Higham's scaling ``2^-s`` from its own 1-norm and the stack shares
    a few batched products and one batched solve. Agrees with ``scipy.linalg.expm`` to about 1e-14 relative
    (``tests/model/test_expm_batched.py``).
    """
    Z = np.asarray(Z, dtype=float)
    n, m, _ = Z.shape
    if n == 0:
        return Z.copy()
    norm = np.abs(Z).sum(axis=1).max(axis=1)  # 1-norm of each matrix
    s = np.maximum(0, np.ceil(np.log2(np.maximum(norm, 1e-300) / _THETA13))).astype(int)
    A = Z * np.ldexp(1.0, -s)[:, None, None]
    eye = np.eye(m)
    A2 = A @ A
    A4 = A2 @ A2
    A6 = A4 @ A2
    b = _PADE13
    U = A @ (A6 @ (b[13] * A6 + b[11] * A4 + b[9] * A2) + b[7] * A6 + b[5] * A4 + b[3] * A2 + b[1] * eye)
    V = A6 @ (b[12] * A6 + b[10] * A4 + b[8] * A2) + b[6] * A6 + b[4] * A4 + b[2] * A2 + b[0] * eye
    X = np.linalg.solve(V - U, V + U)
    for j in range(int(s.max())):  # undo the scaling: square each matrix s times
        more = s > j
        Xm = X[more]
        X[more] = Xm @ Xm
    return X


def _expm_series(survive: np.ndarray, w: np.ndarray, lam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n, nd, _ = survive.shape
    n_c = w.shape[1]
    idle = (w > 0) & (lam <= 0)
    eA = np.sum(w * idle, axis=1)[:, None, None] * np.eye(nd)[None]
    phi = np.zeros((n, nd, nd))
    active = np.flatnonzero((w > 0) & (lam > 0))  # flat (i, c) indices; only these need an expm
    if active.size:
        i = active // n_c
        lam_ic = lam.ravel()[active][:, None, None]
        Z = np.zeros((active.size, 2 * nd, 2 * nd))
        Z[:, :nd, :nd] = lam_ic * (survive[i] - np.eye(nd)[None])
        Z[:, nd:, :nd] = np.eye(nd)[None]
        X = expm_batched(Z)
        wic = w.ravel()[active][:, None, None]
        full = np.zeros((2, n * n_c, nd, nd))
        full[0, active] = wic * X[:, :nd, :nd]
        full[1, active] = wic * lam_ic * X[:, nd:, :nd]
        full = full.reshape(2, n, n_c, nd, nd).sum(axis=2)
        eA, phi = eA + full[0], full[1]
    return eA, phi


def stage_operator(edges_mm: np.ndarray, stats: ImpactStatistics, stage: int, breakage, damage,
                   n_damage: int, n_nodes: int) -> StageOperator:
    """Primary impact with probability ``h``, then Poisson secondary impacts on survivors.

    ``stage`` is the 0-based stage index into the (S, N) arrays of ``stats``
    (:func:`stage_operators` of that stage).
    """
    sub = lambda m: MixtureArrays(m.weights[stage], m.means_m_s[stage], m.sigmas_m_s[stage])  # noqa: E731
    c = stats.count_mixture()
    op = stage_operators(edges_mm, stats.hit_probability[stage], sub(stats.primary_velocity),
                         sub(stats.secondary_velocity), CountArrays(c.weights[stage], c.means[stage]),
                         breakage, damage, n_damage, n_nodes)
    return op


def stage_operators(edges_mm: np.ndarray, hit: np.ndarray, primary: MixtureArrays, secondary: MixtureArrays,
                    counts: CountArrays, breakage, damage, n_damage: int, n_nodes: int) -> StageOperator:
    """Stage operators of any batch of stages: primary impact with probability ``h``, then secondaries.

    Parameters
    ----------
    hit : ndarray (..., N)
        Primary hit probability per size class; the leading axes are the batch
        (e.g. stages, or samples and stages).
    primary, secondary : MixtureArrays
        Velocity mixtures (..., N, K) (m/s).
    counts : CountArrays
        Secondary-count mixtures (..., N, C).

    Returns
    -------
    StageOperator
        Arrays with the batch's leading axes: ``G`` (..., n_s, n_s), the counts
        and energies (..., n_s).
    """
    hit = np.asarray(hit, dtype=float)
    lead, n = hit.shape[:-1], hit.shape[-1]
    nd = n_damage
    ns = n * nd
    flat = lambda m: MixtureArrays(*(np.asarray(a, dtype=float).reshape(-1, n, np.shape(a)[-1])  # noqa: E731
                                     for a in (m.weights, m.means_m_s, m.sigmas_m_s)))
    hh = hit.reshape(-1, n)  # (B, N)
    bsz = hh.shape[0]
    prim = impact_operators(edges_mm, flat(primary), breakage, damage, nd, n_nodes)
    sec = impact_operators(edges_mm, flat(secondary), breakage, damage, nd, n_nodes)
    Sp = prim.survive  # (B, N, nd, nd) blocks of the block-diagonal survivor operator
    cw, cm = (np.asarray(a, dtype=float) for a in (counts.weights, counts.means))
    eA, phi = secondary_series(sec.survive.reshape(-1, nd, nd), cw.reshape(bsz * n, -1), cm.reshape(bsz * n, -1))
    eA, phi = eA.reshape(bsz, n, nd, nd), phi.reshape(bsz, n, nd, nd)
    # after a primary hit: survivors of primary and secondaries, and all fragments (class k)
    phiSp = phi @ Sp
    frag = prim.fragments + np.einsum("bkie,bief->bkif", sec.fragments, phiSp)
    G = np.zeros((bsz, n, nd, n, nd))
    ii = np.arange(n)
    G[:, ii, :, ii, :] = np.moveaxis((eA @ Sp) * hh[..., None, None], 0, 1)
    G[:, :, 0, :, :] += frag * hh[:, None, :, None]
    G = G.reshape(bsz, ns, ns)
    h = np.repeat(hh, nd, axis=-1)  # (B, ns)
    G[:, np.arange(ns), np.arange(ns)] += 1.0 - h
    cnt = phiSp.sum(axis=-2)  # (B, N, nd): expected secondary impacts per primary survivor
    shape = lambda a: a.reshape(*lead, *a.shape[1:])  # noqa: E731
    return StageOperator(
        G=shape(G),
        primary_count=shape(h),
        primary_energy_kwh_t=shape(h * np.repeat(prim.mean_energy_kwh_t, nd, axis=-1)),
        secondary_count=shape((cnt * hh[..., None]).reshape(bsz, ns)),
        secondary_energy_kwh_t=shape((cnt * (sec.mean_energy_kwh_t * hh)[..., None]).reshape(bsz, ns)),
    )


@dataclass(frozen=True)
class LinearMill:
    """The assembled linear system of one mill at one operating point.

    Attributes
    ----------
    M : scipy.sparse.csr_matrix
        Step operator on the flattened state.
    out_op : scipy.sparse.csr_matrix (N, n)
        Product of a step by size class (tonnes).
    impacted : scipy.sparse.csr_matrix (n, n)
        Mass impacted during a step (diagonal).
    stages : list of StageOperator
    n_stages, n_sizes, n_damage : int
    transition : Transition or None
        The transport it was built from; when it depends on the mill's fill
        (``transition.filling``) :meth:`step` uses ``stay`` and ``max_speed``.
    stay : scipy.sparse.csr_matrix or None
        Step operator of a transport that moves nothing (every compartment's
        rock stays and is impacted as staying rock), for fill-dependent speeds.
    max_speed : ndarray (n,) or None
        Largest transport speed per state that keeps the step non-negative.
    """

    M: sp.csr_matrix
    out_op: sp.csr_matrix
    impacted: sp.csr_matrix
    stages: list[StageOperator]
    n_stages: int
    n_sizes: int
    n_damage: int
    feed_compartment: int = 1
    transition: Any = None
    stay: sp.csr_matrix | None = None
    max_speed: np.ndarray | None = None

    @property
    def fill_dependent(self) -> bool:
        """Whether the transport's speed depends on the mill's fill."""
        return self.stay is not None and self.transition is not None and self.transition.filling is not None

    def step(self, x: np.ndarray, fill: float = 1.0) -> tuple[np.ndarray, float]:
        """One step of the mill without feed at mill fill ``fill``: the new state and the mass put out (t).

        At speed ``g`` (:meth:`Transition.speed_at`, capped per state by
        ``max_speed``; one speed per compartment, or per compartment and size class
        with per-class filling curves) the transport of compartment ``c``
        is ``g P_c + (1 - g) I``, so the step is ``M x + (M - stay) ((g - 1) x)`` and the product
        ``out_op (g x)`` (both linear in the transport; ``g = 1``: ``M x``).
        """
        if not self.fill_dependent:
            return self.M @ x, float((self.out_op @ x).sum())
        g = self.transition.speed_at(fill)
        if np.ndim(g):  # per size class (N,): to the state order (compartment, class, damage)
            g = np.tile(np.repeat(g, self.n_damage), self.n_stages + 1)
        g = np.minimum(g, self.max_speed)
        dx = (g - 1.0) * x
        return self.M @ x + (self.M @ dx - self.stay @ dx), float((self.out_op @ (g * x)).sum())

    @property
    def n_state(self) -> int:
        """Length of the flattened state vector."""
        return self.M.shape[0]

    def feed_vector(self, feed_fractions: np.ndarray, tonnes_per_step: float) -> np.ndarray:
        """Fresh feed of one step (undamaged, into the feed compartment) as a state vector (t)."""
        f = np.zeros(self.n_state)
        ns = self.n_sizes * self.n_damage * self.feed_compartment
        f[ns + np.arange(self.n_sizes) * self.n_damage] = np.asarray(feed_fractions) * tonnes_per_step
        return f

    def steady_state(self, f: np.ndarray) -> np.ndarray:
        """Steady state ``x = (I - M)^-1 f`` by one sparse direct solve."""
        A = sp.identity(self.n_state, format="csc") - self.M.tocsc()
        x = spla.spsolve(A, f, permc_spec="MMD_AT_PLUS_A")  # fastest ordering for this block structure
        if not np.all(np.isfinite(x)):
            raise MsmillError("the mill never empties (no outflow for some rock); "
                              "check the bottom stage's pass-through")
        return np.maximum(x, 0.0)


def assemble(edges_mm: np.ndarray, streams, stats: ImpactStatistics, breakage, damage,
             n_damage: int, n_nodes: int, impacted: str = "refeed") -> LinearMill:
    """Assemble the step operator of the whole mill.

    Parameters
    ----------
    edges_mm : ndarray (N+1,)
        Size-class edges (mm).
    streams : Transition or ndarray (S, N, 3)
        One-step transport of every compartment (:class:`msmill.model.submodels.Transition`),
        or ``[kickback, refeed, pass_through]`` per stage and size class.
    stats : ImpactStatistics
        Impact statistics (S, N).
    breakage, damage
        Sub-models.
    n_damage : int
        Number of damage classes.
    n_nodes : int
        Gauss-Hermite nodes per mixture component.
    impacted : {"refeed", "all"}
        Which mass is impacted in a step (see docs/model.md): the mass that stays
        in its stage, or all of a stage's mass before it moves.
    """
    tr = as_transition(streams)
    T = tr.matrix  # (C, N, C+1), C = S + 1 compartments
    n_st = tr.n_stages
    n = edges_mm.size - 1
    nd = n_damage
    batch = stage_operators(edges_mm, stats.hit_probability, stats.primary_velocity, stats.secondary_velocity,
                            stats.count_mixture(), breakage, damage, nd, n_nodes)  # all stages at once
    stage_ops = [StageOperator(*(getattr(batch, f.name)[s] for f in dataclasses.fields(StageOperator)))
                 for s in range(n_st)]
    if impacted not in ("refeed", "all"):  # pragma: no cover - validated by Mill
        raise ValueError(impacted)

    M, out_op, imp = _step_matrices(T, batch.G, n, nd, impacted)
    stay = max_speed = None
    if tr.filling is not None:
        stay = _step_matrices(tr.staying(), batch.G, n, nd, impacted)[0]
        cap = tr.max_speed()  # (C,) or per class (C, N); state order (compartment, class, damage)
        max_speed = np.repeat(cap.ravel(), nd if cap.ndim == 2 else n * nd)
    return LinearMill(M=M, out_op=out_op, impacted=imp, stages=stage_ops, n_stages=n_st, n_sizes=n, n_damage=nd,
                      feed_compartment=tr.feed_compartment, transition=tr, stay=stay, max_speed=max_speed)


def _step_matrices(T: np.ndarray, G: np.ndarray, n: int, nd: int, impacted: str) -> tuple[sp.csr_matrix, ...]:
    """Step operator ``M``, product operator and impacted-mass operator, built as one COO each.

    ``T`` (C, N, C+1) transitions, ``G`` (S, ns, ns) stage operators. Block
    ``(c2, c)`` of ``M`` moves compartment ``c``'s mass to ``c2``
    (``diag(T[c, :, c2])`` per damage class); a stage's impacts act on the
    mass that stays (``"refeed"``: block ``(c, c)`` is ``G_c diag(T_cc)``) or on
    all its mass before it moves (``"all"``: blocks ``diag(T_c.) G_c``).
    """
    n_c = T.shape[0]
    ns = n * nd
    t = np.repeat(T, nd, axis=1)  # (C, ns, C+1): per state
    k = np.arange(ns)
    rows, cols, vals = [], [], []
    o_rows, o_cols, o_vals = [], [], []

    def add(r, c, v, out=False):
        keep = v != 0.0
        (o_rows if out else rows).append(r[keep])
        (o_cols if out else cols).append(c[keep])
        (o_vals if out else vals).append(v[keep])

    for c in range(n_c):
        impacts = c >= 1
        for c2 in range(n_c + 1):
            out = c2 == n_c
            if not impacts or (impacted == "refeed" and c2 != c):  # a move (the inlet zone is not impacted)
                add(k // nd if out else c2 * ns + k, c * ns + k, t[c, :, c2], out)
                continue
            B = G[c - 1] * t[c, :, c2][None, :] if impacted == "refeed" else t[c, :, c2][:, None] * G[c - 1]
            if out:
                B = B.reshape(n, nd, ns).sum(axis=1)
            r, q = np.nonzero(B)
            add(r if out else c2 * ns + r, c * ns + q, B[r, q], out)
    size = n_c * ns
    M = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(size, size))
    out_op = sp.csr_matrix((np.concatenate(o_vals), (np.concatenate(o_rows), np.concatenate(o_cols))),
                           shape=(n, size))
    d = np.concatenate([np.zeros(ns)] + [t[c, :, c] if impacted == "refeed" else np.ones(ns)
                                          for c in range(1, n_c)])
    return M, out_op, sp.diags(d, format="csr")


#: Members solved together by :func:`steady_products` (more go in chunks of this many).
STEADY_CHUNK_MEMBERS = 64


def steady_products(edges_mm: np.ndarray, transports: list, stats: list[ImpactStatistics], breakage, damage,
                    n_damage: int, n_nodes: int, impacted: str, feed_fractions: np.ndarray,
                    tonnes_per_step: np.ndarray) -> np.ndarray:
    """Steady-state product of a batch of mills (e.g. posterior samples), solved together.

    Equal (to rounding) to ``assemble(...).out_op @ assemble(...).steady_state(f)``
    for each member, but batched: the stage operators of all members and
    stages in one :func:`stage_operators` call, then one sweep over the size
    classes from the top (:func:`_size_sweep`): rock only moves between
    compartments and damage classes within its size class or breaks into
    smaller (or the same) classes, so ``(I - M) x = f`` is block-triangular in
    size and each class is a small dense solve of (compartments x damage
    classes) unknowns for all members at once. Members that cannot be stacked
    (different shapes or feed compartments) or breakage that puts mass above
    its parent class go through :func:`assemble` one by one; more than
    :data:`STEADY_CHUNK_MEMBERS` members are solved in chunks of that many.

    Parameters
    ----------
    transports : list of Transition or ndarray (S, N, 3)
        One-step transport of every member.
    stats : list of ImpactStatistics
        Impact statistics (S, N) of every member.
    feed_fractions : ndarray (N,) or (N, K)
        Feed mass fractions per size class (K feeds at once: e.g. the identity gives every
        member's transfer matrix, product per class per unit feed per class).
    tonnes_per_step : ndarray (B,)
        Feed of one step of every member (t).

    Returns
    -------
    ndarray (B, N), or (B, N, K) for K feeds
        Product of one step at steady state by size class (t).
    """
    trs = [as_transition(t) for t in transports]
    tps = np.asarray(tonnes_per_step, dtype=float)
    k = STEADY_CHUNK_MEMBERS
    if len(trs) > k:  # bounded memory (stage operators of 64 members: ~20 MB at 21 classes, 4 damage classes)
        return np.concatenate([steady_products(edges_mm, trs[i:i + k], stats[i:i + k], breakage, damage, n_damage,
                                               n_nodes, impacted, feed_fractions, tps[i:i + k])
                               for i in range(0, len(trs), k)])
    stacked = _stack_members(trs, stats)
    if stacked is not None:
        T, hit, prim, sec, counts = stacked
        ops = stage_operators(edges_mm, hit, prim, sec, counts, breakage, damage, n_damage, n_nodes)
        b, n_st, n = hit.shape
        G4 = ops.G.reshape(b, n_st, n, n_damage, n, n_damage)
        if not np.any(G4.transpose(0, 1, 3, 5, 2, 4)[..., np.tril(np.ones((n, n), dtype=bool), -1)]):
            ff = np.asarray(feed_fractions, dtype=float)
            f = np.zeros((b, n_st + 1, n, n_damage, *ff.shape[1:]))
            f[:, trs[0].feed_compartment, :, 0] = ff[None] * tps.reshape(-1, *(1,) * ff.ndim)
            return _size_sweep(T, G4, ops.G, f, impacted)
    out = []
    for tr, st, t in zip(trs, stats, tps, strict=True):
        lm = assemble(edges_mm, tr, st, breakage, damage, n_damage, n_nodes, impacted)
        ff = np.asarray(feed_fractions, dtype=float)
        cols = [np.asarray(lm.out_op @ lm.steady_state(lm.feed_vector(c, t))) for c in ff.reshape(ff.shape[0], -1).T]
        out.append(np.stack(cols, axis=-1).reshape(ff.shape))
    return np.array(out)


def _stack_members(trs: list, stats: list[ImpactStatistics]) -> tuple | None:
    """Transition matrices (B, C, N, C+1) and the stats' arrays with a leading member axis, or None."""
    if len({(t.matrix.shape, t.feed_compartment) for t in trs}) != 1:
        return None
    counts = [s.count_mixture() for s in stats]
    arrays = {"hit": [s.hit_probability for s in stats], "cw": [c.weights for c in counts],
              "cm": [c.means for c in counts]}
    for kind in ("primary_velocity", "secondary_velocity"):
        for f in ("weights", "means_m_s", "sigmas_m_s"):
            arrays[kind[0] + f] = [getattr(getattr(s, kind), f) for s in stats]
    if any(len({np.shape(a) for a in v}) != 1 for v in arrays.values()):
        return None
    a = {k: np.stack([np.asarray(x, dtype=float) for x in v]) for k, v in arrays.items()}
    mix = lambda p: MixtureArrays(a[p + "weights"], a[p + "means_m_s"], a[p + "sigmas_m_s"])  # noqa: E731
    return (np.stack([t.matrix for t in trs]), a["hit"], mix("p"), mix("s"), CountArrays(a["cw"], a["cm"]))


def _size_sweep(T: np.ndarray, G4: np.ndarray, G: np.ndarray, f: np.ndarray, impacted: str) -> np.ndarray:
    """Steady state of a batch of mills by size class from the top; returns the product (B, N) (t/step).

    ``T`` (B, C, N, C+1) transitions, ``G4`` the stage operators (B, S, N, nd, N, nd)
    (``G`` the same as (B, S, ns, ns)), ``f`` the feed of one step (B, C, N, nd), or
    (B, C, N, nd, K) for K feeds at once (then the product is (B, N, K)).
    With ``impacted="refeed"`` a stage's operator acts on the mass that stays
    (``G_c T_cc``), with ``"all"`` on all its mass before it moves (``T_c. G_c``).
    """
    if f.ndim == 4:
        return _size_sweep(T, G4, G, f[..., None], impacted)[..., 0]
    b, n_c, n, nd, k = f.shape
    m = n_c * nd
    ii = np.arange(n)
    Gd = np.moveaxis(G4[:, :, ii, :, ii, :], 0, 2)  # (B, S, N, nd, nd): within-class blocks
    Tt = np.moveaxis(T[..., :n_c], 1, -1)  # (B, N, C2, C)
    A = Tt[:, :, :, None, :, None] * np.eye(nd)[:, None, :]  # (B, N, C2, nd, C, nd): moves
    stay = np.moveaxis(T[:, 1:, :, 1:][:, np.arange(n_c - 1), :, np.arange(n_c - 1)], 0, 1)  # (B, S, N)
    for c in range(1, n_c):
        if impacted == "refeed":
            A[:, :, c, :, c, :] = Gd[:, c - 1] * stay[:, c - 1, :, None, None]
        else:
            A[:, :, :, :, c, :] = Tt[:, :, :, c, None, None] * Gd[:, c - 1][:, :, None]
    A = np.eye(m) - A.reshape(b, n, m, m)
    x = np.zeros((b, n_c, n, nd, k))
    h = np.zeros((b, n_c - 1, n, nd, k))  # fragments from larger classes, per stage and class
    for i in range(n - 1, -1, -1):
        r = f[:, :, i].copy()
        if impacted == "refeed":
            r[:, 1:] += h[:, :, i]
        else:
            r += np.einsum("bcs,bsdk->bcdk", Tt[:, i, :, 1:], h[:, :, i])
        try:
            x[:, :, i] = np.linalg.solve(A[:, i], r.reshape(b, m, k)).reshape(b, n_c, nd, k)
        except np.linalg.LinAlgError:
            x[:, :, i] = np.nan
        u = x[:, 1:, i] * (stay[:, :, i, None, None] if impacted == "refeed" else 1.0)  # (B, S, nd, K)
        h[:, :, :i] += np.einsum("bsjxd,bsdk->bsjxk", G4[:, :, :i, :, i, :], u)
    if not np.all(np.isfinite(x)):
        raise MsmillError("the mill never empties (no outflow for some rock); check the bottom stage's pass-through")
    x = np.maximum(x, 0.0)
    if impacted == "refeed":
        return np.einsum("bcn,bcnk->bnk", T[..., -1], x.sum(axis=3))
    hit = (G @ x[:, 1:].reshape(b, n_c - 1, n * nd, k)).reshape(b, n_c - 1, n, nd, k)
    return (T[:, 0, :, -1, None] * x[:, 0].sum(axis=2)
            + np.einsum("bcn,bcnk->bnk", T[:, 1:, :, -1], hit.sum(axis=3)))
