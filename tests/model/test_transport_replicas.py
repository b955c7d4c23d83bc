"""The replica analysis of msmill.model.transport_check on SYNTHETIC hold-up series (analytic fills)."""

import numpy as np
import pytest

from msmill.dem.mill.run import RunSettings
from msmill.errors import MsmillInputError
from msmill.model import transport_check as B
from msmill.steadystate import first_steady

FEED = 2.0  # kg/s


def replica(tau_s: float, end_s: float = 6.0, every_s: float = 0.01, seed: int = 1) -> dict:
    """SYNTHETIC replica: a well-mixed mill of residence tau filling from empty, H = F tau (1 - e^-t/tau)."""
    t = np.round(np.arange(0.0, end_s + 1e-9, every_s), 5)
    held = FEED * tau_s * (1 - np.exp(-t / tau_s))
    out = FEED * t - held  # mass balance: fed = held + out
    t = np.insert(t, 50, t[50])  # a repeated sample time, as a coarse record downsampled gives
    held, out = np.insert(held, 50, held[50]), np.insert(out, 50, out[50])
    return {"size_mm": 20.0, "seed": seed, "feed_kg_s": FEED, "residence_time_s": None,
            "series": {"time_s": t.tolist(), "holdup_kg": held.tolist(), "product_cum_kg": out.tolist()}}


def test_onset_and_residence_of_one_replica():
    crit = RunSettings().criterion()
    r = replica(1.0)
    t, h, q = B.replica_series(r)
    assert np.all(np.diff(t) > 0)  # the repeated time is dropped
    onset = B.replica_onset(r, crit)
    assert onset == first_steady(t, h, q, FEED, crit)[0]
    assert 1.0 < onset < 4.0
    # Little's law over the steady part: hold-up / rate -> tau (the tail of the fill is e^-onset small)
    assert B.replica_residence(r, onset) == pytest.approx(1.0, rel=0.08)
    # less than 1 s of steady series, or never steady: the run's own window figure
    assert B.replica_residence({**r, "residence_time_s": 0.9}, 5.5) == 0.9
    assert B.replica_residence({**r, "residence_time_s": 0.9}, float("nan")) == 0.9


def test_ensemble_is_the_mean_series_and_its_onset_lies_between():
    crit = RunSettings().criterion()
    fast, slow = replica(0.6, end_s=6.0), replica(1.4, end_s=5.0, seed=2)
    t, h, q, f = B.ensemble_series([fast, slow])
    assert t[-1] == pytest.approx(5.0) and f == FEED  # to the shorter series
    k = np.searchsorted(t, 2.0)
    assert h[k] == pytest.approx(0.5 * (FEED * 0.6 * (1 - np.exp(-2 / 0.6)) + FEED * 1.4 * (1 - np.exp(-2 / 1.4))),
                                 rel=1e-6)
    o_fast, o_slow = B.replica_onset(fast, crit), B.replica_onset(slow, crit)
    o_mean = first_steady(t, h, q, f, crit)[0]
    assert o_fast < o_mean <= o_slow + 1e-9


def test_attach_replicas_fills_the_row_and_its_error():
    crit = RunSettings().criterion()
    reps = [replica(1.0, seed=s) for s in range(4)]
    row = B.Row(20.0, 0.03, 1.0, 1.05, 2.0, 2.0, 2.0, 2.0, False, tss_model_today_s=2.5)
    B.attach_replicas(row, reps, crit)
    assert row.n_replicas == 4
    assert row.tss_dem_rep_s == pytest.approx(B.replica_onset(reps[0], crit))  # identical replicas
    assert row.tss_err_rep == pytest.approx(2.5 - row.tss_dem_rep_s)
    assert row.res_err_rep == pytest.approx((1.05 - row.res_dem_rep_s) / row.res_dem_rep_s)
    assert row.tss_dem_rep_se_s == pytest.approx(0.0, abs=1e-12)  # resampling identical runs changes nothing
    other = B.Row(14.0, 0.03, 1.0, 1.05, 2.0, 2.0, 2.0, 2.0, False)
    assert B.attach_replicas(other, reps, crit).n_replicas == 0  # replicas of another size are not used
    assert other.tss_err_rep == other.tss_err


def _two_compartments(filling=None) -> "B.Transition":
    """SYNTHETIC transport: the inlet zone keeps 30 % a step, the stage keeps 80 % and sends 20 % out."""
    m = np.array([[0.3, 0.7, 0.0], [0.0, 0.8, 0.2]])[:, None, :]
    return B.Transition(m, feed_compartment=0, filling=filling)


def _mean_field_onset(tr, rocks_per_step: float, tau_s: float, crit) -> float:
    """The deterministic march of the same rule (expected rocks, speed at the expected fill)."""
    base = tr.matrix[:, 0, :]
    steady = rocks_per_step * float(B.chain_visits(base).sum())
    steps = int(np.ceil(8.0 / tau_s))
    x, held, out = np.zeros(2), [0.0], [0.0]
    for _ in range(steps):
        p = tr.at_speed(tr.speed_at(x.sum() / steady))[:, 0, :]
        new = x @ p
        x = new[:2].copy()
        x[0] += rocks_per_step
        held.append(x.sum())
        out.append(out[-1] + new[2])
    t = np.arange(steps + 1) * tau_s
    return first_steady(t, np.array(held), np.array(out), rocks_per_step / tau_s, crit)[0]


@pytest.mark.parametrize("filling", [None, (np.array([0.2, 0.6]), np.array([0.3, 0.7]))])
def test_independent_rocks_average_to_the_mean_field_march_when_there_are_many(filling):
    """With 100 rocks fed per step the rock-count noise is small: the ensemble-mean series' onset is the
    deterministic march's, with and without a fill-dependent speed, and the fill dependence is used (rock
    moving faster while the mill is emptier leaves the hold-up creeping up to its plateau: a later onset)."""
    crit = RunSettings().criterion()
    tr = _two_compartments(filling)
    singles, ens = B.scatter_onsets(tr, 100.0, 0.05, crit, n_sims=40, seed=2)
    mf = _mean_field_onset(tr, 100.0, 0.05, crit)
    assert ens == pytest.approx(mf, abs=0.051)
    assert np.nanmedian(singles) == pytest.approx(mf, abs=0.15)
    if filling is not None:
        assert mf > _mean_field_onset(_two_compartments(None), 100.0, 0.05, crit) + 0.3


def test_a_file_that_is_not_a_replicas_file_is_one_line_naming_it(tmp_path):
    bad = tmp_path / "x.json"
    for text in ("not json", '{"kind": "something_else", "replicas": []}', "[1, 2]"):
        bad.write_text(text)
        with pytest.raises(MsmillInputError, match=r"replicas.*x\.json"):
            B.load_replicas(bad)
    assert B.load_replicas(tmp_path / "missing.json") == []


def test_the_approach_plot_draws_a_column_per_size_with_replicas():
    from msmill.plots.validation import approach_plot

    crit = RunSettings().criterion()
    reps = [replica(1.0, seed=s) for s in range(3)]
    t = np.linspace(0, 6, 61)
    rows = [B.Row(20.0, 0.03, 1.0, 1.05, 2.0, 2.0, 2.0, 2.0, False, tss_model_today_s=2.5,
                  model_series=(t, 1 - np.exp(-t), 1 - np.exp(-t))),
            B.Row(14.0, 0.03, 1.0, 1.05, 2.0, 2.0, 2.0, 2.0, False)]
    for r in rows:
        B.attach_replicas(r, reps, crit)
    fig = approach_plot(rows, reps)
    assert len(fig.axes) == 2  # hold-up and product rate of the one size with replicas
    assert "3 runs" in fig.axes[0].get_legend().get_texts()[0].get_text()
    with pytest.raises(MsmillInputError, match="replicas"):
        approach_plot(rows[1:], reps)
