"""The batched expected-value paths equal the one-at-a-time ones (all stage parameters SYNTHETIC).

Reference implementations here are the previous code paths: the one-impact
operator by one-hot einsums, scipy's fractional matrix power per class,
``np.interp`` of the damage table, and ``assemble(...).steady_state`` per member.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
from test_mass_balance import BREAKAGE, DAMAGE, GRID, ORE, random_parameters

from msmill.model import expected_value as ev
from msmill.model.parameters import CountArrays, MixtureArrays
from msmill.model.submodels import (
    ImpactStatistics,
    JkT10Breakage,
    NoBreakage,
    Transition,
    _to_step,
    fractional_powers,
    specific_energy_kwh_t,
)

EDGES = GRID.edges_mm
N = GRID.n_classes


def reference_impact_operator(edges_mm, mix, breakage, damage, nd, n_nodes):
    """The previous one-stage impact operator (one-hot einsums, fragments column by column)."""
    mids = np.sqrt(edges_mm[:-1] * edges_mm[1:])
    th = float(damage.threshold)
    dn = ev.damage_nodes(nd, th)
    v, w = ev.quadrature(mix, n_nodes)
    e = specific_energy_kwh_t(v)
    L = mids[:, None, None]
    pb = breakage.probability(e[..., None], L, dn[None, None, :])
    d_new = damage.after_impact(e[..., None], L, dn[None, None, :])
    broke = d_new >= th
    pbr = pb + (1.0 - pb) * broke
    parent = np.broadcast_to(np.arange(mids.size)[:, None, None], pb.shape)
    frag = np.einsum("iq,iqd,iqdk->kid", w, pbr, breakage.fragments(edges_mm, parent, pb))
    surv = w[..., None] * (1.0 - pbr)
    lo, frac = ev.split_damage(np.where(broke, 0.0, d_new), nd, th)
    classes = np.arange(nd)
    S = (np.einsum("iqd,iqde->ied", surv * (1.0 - frac), lo[..., None] == classes)
         + np.einsum("iqd,iqde->ied", surv * frac, (lo + 1)[..., None] == classes))
    return S, frag, np.sum(w * e, axis=-1)


def random_mix(rng, shape, k=3):
    return MixtureArrays(rng.dirichlet(np.ones(k), size=shape), rng.uniform(-5, 70, (*shape, k)),
                         rng.uniform(0.5, 15, (*shape, k)))


@pytest.mark.parametrize("breakage", [BREAKAGE, JkT10Breakage(ORE), NoBreakage()], ids=lambda b: b.name)
def test_batched_impact_operators_equal_the_one_stage_reference(breakage, monkeypatch):
    monkeypatch.setattr(ev, "BATCH_ELEMENTS", 2000)  # forces several chunks
    rng = np.random.default_rng(3)
    mix = random_mix(rng, (7, N))
    op = ev.impact_operators(EDGES, mix, breakage, DAMAGE, 4, 5)
    for b in range(7):
        ref = reference_impact_operator(EDGES, MixtureArrays(mix.weights[b], mix.means_m_s[b], mix.sigmas_m_s[b]),
                                        breakage, DAMAGE, 4, 5)
        for got, want in zip((op.survive[b], op.fragments[b], op.mean_energy_kwh_t[b]), ref, strict=True):
            np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)


def test_stage_operators_of_a_batch_equal_each_stage_alone():
    rng = np.random.default_rng(5)
    shape = (2, 3, N)  # (samples, stages, sizes)
    counts = CountArrays(rng.dirichlet(np.ones(2), size=shape), rng.uniform(0, 30, (*shape, 2)))
    hit = rng.uniform(0, 1, shape)
    prim, sec = random_mix(rng, shape), random_mix(rng, shape, k=2)
    batch = ev.stage_operators(EDGES, hit, prim, sec, counts, BREAKAGE, DAMAGE, 3, 4)
    for b in range(2):
        stats = ImpactStatistics(hit[b], MixtureArrays(*(a[b] for a in (prim.weights, prim.means_m_s, prim.sigmas_m_s))),
                                 counts.mean()[b],
                                 MixtureArrays(*(a[b] for a in (sec.weights, sec.means_m_s, sec.sigmas_m_s))),
                                 CountArrays(counts.weights[b], counts.means[b]))
        for s in range(3):
            one = ev.stage_operator(EDGES, stats, s, BREAKAGE, DAMAGE, 3, 4)
            np.testing.assert_allclose(batch.G[b, s], one.G, rtol=1e-12, atol=1e-15)
            np.testing.assert_allclose(batch.secondary_energy_kwh_t[b, s], one.secondary_energy_kwh_t, rtol=1e-12)


def _members(rng, n_members, matrix):
    transports, stats = [], []
    for _ in range(n_members):
        streams, st = random_parameters(rng, 3)
        if matrix:  # a one-lag matrix with jumps over stages and an inlet zone (feed compartment 0)
            T = rng.dirichlet(np.ones(5), size=(4, N))
            T[-1, :, -1] += 0.1
            transports.append(Transition(T / T.sum(axis=-1, keepdims=True), feed_compartment=0))
        else:
            transports.append(streams)
        stats.append(st)
    return transports, stats


@pytest.mark.parametrize("impacted", ["refeed", "all"])
@pytest.mark.parametrize("matrix", [True, False], ids=["dem_matrix", "streams"])
def test_steady_products_equal_assemble_one_by_one(impacted, matrix, monkeypatch):
    monkeypatch.setattr(ev, "STEADY_CHUNK_MEMBERS", 2)  # 5 members: chunks of 2, 2, 1
    rng = np.random.default_rng(11)
    transports, stats = _members(rng, 5, matrix)
    feed = rng.dirichlet(np.ones(N))
    tps = rng.uniform(0.1, 2.0, 5)
    got = ev.steady_products(EDGES, transports, stats, BREAKAGE, DAMAGE, 3, 4, impacted, feed, tps)
    for b in range(5):
        lm = ev.assemble(EDGES, transports[b], stats[b], BREAKAGE, DAMAGE, 3, 4, impacted)
        want = lm.out_op @ lm.steady_state(lm.feed_vector(feed, tps[b]))
        np.testing.assert_allclose(got[b], want, rtol=1e-10, atol=1e-14 * tps[b])
        assert got[b].sum() == pytest.approx(tps[b], rel=1e-10)  # steady state: product = feed


class UpwardBreakage(JkT10Breakage):
    """SYNTHETIC breakage that puts some fragment mass one class above the parent."""

    def expected_fragments(self, edges_mm, pb, weights):
        F = super().expected_fragments(edges_mm, pb, weights)
        up = 0.1 * F[:-1]
        F[:-1] -= up
        F[1:] += up
        return F


def test_steady_products_fall_back_when_fragments_go_up():
    rng = np.random.default_rng(2)
    transports, stats = _members(rng, 3, True)
    feed, tps = rng.dirichlet(np.ones(N)), np.ones(3)
    brk = UpwardBreakage(ORE)
    got = ev.steady_products(EDGES, transports, stats, brk, DAMAGE, 2, 3, "refeed", feed, tps)
    for b in range(3):
        lm = ev.assemble(EDGES, transports[b], stats[b], brk, DAMAGE, 2, 3, "refeed")
        np.testing.assert_allclose(got[b], lm.out_op @ lm.steady_state(lm.feed_vector(feed, 1.0)), rtol=1e-10)


def test_secondary_series_rows_of_very_different_lengths_equal_expm():
    rng = np.random.default_rng(4)
    n, nd = 12, 3
    S = rng.uniform(0, 1, (n, nd, nd))
    S *= rng.uniform(0.2, 1.0, (n, 1, nd)) / S.sum(axis=1, keepdims=True)
    lam = np.array([0.0, 0.01, 0.5, 2, 5, 20, 60, 90, 150, 300, 800, 3000.0])
    w = np.c_[np.full(n, 0.3), np.full(n, 0.7)]
    m = np.c_[0.2 * lam, lam]
    a, b = ev.secondary_series(S, w, m), ev.secondary_series(S, w, m, "expm")
    np.testing.assert_allclose(a[0], b[0], atol=1e-13)
    np.testing.assert_allclose(a[1], b[1], rtol=1e-11, atol=1e-12)


def test_fractional_powers_equal_scipy_also_for_defective_matrices():
    rng = np.random.default_rng(8)
    Q = rng.dirichlet(np.ones(5), size=30)  # stochastic rows
    Q = np.stack([np.vstack([q.reshape(1, 5).repeat(4, 0) * rng.uniform(0.5, 1, (4, 1)), np.eye(5)[4]]) for q in Q])
    Q[:, :4, :4] += np.eye(4) * (1 - Q[:, :4].sum(axis=-1))[:, :, None]
    Q[0] = [[0.5, 0.5, 0, 0, 0], [0, 0.5, 0.5, 0, 0], [0, 0, 0.5, 0.5, 0], [0, 0, 0, 0.5, 0.5], [0, 0, 0, 0, 1]]
    p = rng.uniform(0.7, 1.3, Q.shape[0])  # Q[0] is a Jordan block: eigenvectors ill-conditioned
    got = fractional_powers(Q, p)
    want = np.array([np.real(scipy.linalg.fractional_matrix_power(q, e)) for q, e in zip(Q, p, strict=True)])
    np.testing.assert_allclose(got, want, atol=1e-12)


def test_to_step_is_the_identity_at_equal_lag_and_normalised():
    rng = np.random.default_rng(9)
    T = rng.dirichlet(np.ones(6), size=(5, N))
    lag = np.full(N, 0.05)
    lag[::2] = 0.06
    out = _to_step(T, lag, 0.05)
    np.testing.assert_array_equal(out[:, 1::2], T[:, 1::2])
    np.testing.assert_allclose(out.sum(axis=-1), 1.0)
    assert np.all(out >= 0.0)


def test_tavares_table_lookup_equals_np_interp():
    r = np.concatenate([np.random.default_rng(0).uniform(0, 1, 10000), DAMAGE._r, [0.0, np.nextafter(1.0, 0.0)]])
    j = np.minimum((r * (DAMAGE._r.size - 1)).astype(np.intp), DAMAGE._r.size - 2)
    np.testing.assert_allclose(DAMAGE._dd[j] + (r - DAMAGE._r[j]) * DAMAGE._slope[j],
                               np.interp(r, DAMAGE._r, DAMAGE._dd), rtol=0, atol=1e-15)
    e = np.linspace(0.0, 3.0, 50)
    d_new = DAMAGE.after_impact(e, 10.0, 0.2)
    from msmill import breakage as bk

    ratio = bk.survivor_energy_ratio(e, 10.0, ORE.b_t_per_kwh, ORE.l_ref_mm, 0.2)
    want = 1.0 - 0.8 * (1.0 - np.interp(ratio, DAMAGE._r, DAMAGE._dd))
    np.testing.assert_allclose(d_new, want, rtol=0, atol=1e-15)


@pytest.mark.parametrize("impacted", ["refeed", "all"])
@pytest.mark.parametrize("fallback", [False, True], ids=["batched", "one_by_one"])
def test_steady_products_of_several_feeds_are_each_feeds_products(impacted, fallback):
    """Feeds (N, K) at once (the identity: every member's transfer matrix, as circuits use it) give each
    column's product, on the batched sweep and on the one-by-one fallback."""
    rng = np.random.default_rng(7)
    transports, stats = _members(rng, 3, True)
    brk = UpwardBreakage(ORE) if fallback else BREAKAGE
    feeds = np.column_stack([rng.dirichlet(np.ones(N)) for _ in range(4)])
    tps = rng.uniform(0.1, 2.0, 3)
    got = ev.steady_products(EDGES, transports, stats, brk, DAMAGE, 2, 3, impacted, feeds, tps)
    assert got.shape == (3, N, 4)
    for k in range(4):
        one = ev.steady_products(EDGES, transports, stats, brk, DAMAGE, 2, 3, impacted, feeds[:, k], tps)
        np.testing.assert_allclose(got[..., k], one, rtol=1e-10, atol=1e-14)
    eye = ev.steady_products(EDGES, transports, stats, brk, DAMAGE, 2, 3, impacted, np.eye(N), np.ones(3))
    np.testing.assert_allclose(np.einsum("bij,jk->bik", eye, feeds) * tps[:, None, None], got, rtol=1e-9, atol=1e-14)
