"""The campaign's results analysis (msmill.pipeline.results): on the shipped export (our DEM runs), the shipped
table's runs, and HAND-MADE or SYNTHETIC points and series where a known answer is needed."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from msmill.errors import MsmillInputError
from msmill.pipeline import results as R
from msmill.stageparams import RunStatistics
from msmill.surrogate.accuracy import FINE_SIZE_MM, loo_scores
from msmill.surrogate.capacity import CapacityModel, EnvelopePoint


def synthetic_points(n: int = 40, seed: int = 1) -> list[EnvelopePoint]:
    """SYNTHETIC runs of a capacity law (t/h) rising with size, speed and gate; choked above it."""
    rng = np.random.default_rng(seed)
    size, speed = np.exp(rng.uniform(np.log(2), np.log(30), n)), rng.uniform(1200, 1900, n)
    gate, feed = rng.uniform(0, 80, n), rng.uniform(10, 60, n)
    cap = 15.0 + 8.0 * np.log(size / 2.0) + 0.01 * (speed - 1200.0) + 0.15 * gate
    return [EnvelopePoint(s, f, v, g, "choked" if f > c else "steady", c if f > c else f)
            for s, f, v, g, c in zip(size, feed, speed, gate, cap, strict=True)]


@pytest.fixture(scope="module")
def campaign():
    return R.load_campaign()


def test_load_campaign_splits_the_export(campaign):
    assert len(campaign.slices) >= R.MIN_SLICE_RUNS
    assert {r.path for r in campaign.slices + campaign.fulls} <= {r.path for r in campaign.all_runs}
    assert all(r.outcome == "steady" and r.mode == "slice" for r in campaign.slices)


def test_load_campaign_errors_name_the_option(tmp_path):
    with pytest.raises(MsmillInputError, match=r"^--export: .*existing campaign export folder"):
        R.load_campaign(tmp_path / "missing")
    with pytest.raises(MsmillInputError, match=r"^--export: .*at least 4 steady slice runs.*has 0 of 0"):
        R.load_campaign(tmp_path)


def test_run_table_has_one_row_per_steady_slice_run(campaign):
    t = R.run_table(campaign.slices)
    assert len(t) == len(campaign.slices) and t["file"].is_unique
    assert list(t["date"]) == sorted(t["date"])  # computation order
    r = next(x for x in campaign.slices if x.path.name == t["file"].iloc[-1])
    row = t.iloc[-1]
    assert (row["size_mm"], row["feed_tph"], row["speed_rpm"], row["gate_deg"]) == r.statistics.design.inputs()
    for s in r.statistics.stages:
        assert row[f"s{s.stage}.refeed"] == s.refeed
        assert row[f"s{s.stage}.hit_probability"] == s.primary_hit_probability
    assert row["sampling_kl"] == R.sampling_kl(r.statistics)


def test_sampling_kl_is_set_by_the_fewest_impacts(table_runs):
    from msmill.dem.mill.run import VELOCITY_FIT_PARAMETERS

    st = table_runs[0]
    counts = [(100 + 10 * i, 900 - 10 * i) for i in range(len(st.stages))]  # HAND-MADE: fewest 100 primary
    counts[-1] = (400, 60)  # ... and 60 secondary in the bottom stage
    doc = st.model_dump(mode="json")
    for s, (p, q) in zip(doc["stages"], counts, strict=True):
        s["n_primary_impacts"], s["n_secondary_impacts"] = p, q
    assert R.sampling_kl(RunStatistics.from_dict(doc)) == VELOCITY_FIT_PARAMETERS / (2 * 60)


def test_learning_curve_uses_the_first_n_runs_in_the_given_order(campaign):
    slices = campaign.slices[:8]
    order = [r.path.name for r in slices]
    fwd = R.learning_curve(slices, order, n_points=3)
    rev = R.learning_curve(slices, order[::-1], n_points=3)
    assert list(fwd["runs"]) == [4, 6, 8] == list(rev["runs"])
    assert set(fwd.columns) == {"runs", "kl_velocity", "kl_count", "stream_mae", "hit_mae", "representation_kl",
                                "runs_fine", "kl_velocity_fine"}
    fine = [r.statistics.design.size_mm < FINE_SIZE_MM for r in slices]
    assert list(fwd["runs_fine"]) == [sum(fine[:n]) for n in (4, 6, 8)]
    # all 8 runs: the same whatever the order; the first 4 differ between the two orders
    pd.testing.assert_series_equal(fwd.iloc[-1], rev.iloc[-1], rtol=1e-6)
    assert fwd["kl_velocity"].iloc[0] != pytest.approx(rev["kl_velocity"].iloc[0], rel=1e-6)
    assert (fwd[["kl_velocity", "kl_count", "representation_kl"]] > 0).all().all()


def test_hours_by_size_band_sums_each_band():
    """HAND-MADE runs: sizes on and between the band edges, wall times in seconds."""
    runs = pd.DataFrame({"size_mm": [1.5, 2.0, 3.9, 4.0, 6.4, 30.0, 25.0],
                         "wall_s": [3600.0, 7200.0, 1800.0, 900.0, 600.0, 360.0, np.nan]})
    t = R.hours_by_size_band(runs)
    assert list(t["band"]) == ["< 2 mm", "2-4 mm", "4-6.4 mm", "6.4-10 mm", "10-20 mm", "20-30 mm"]
    assert list(t["runs"]) == [1, 2, 1, 1, 0, 2]
    np.testing.assert_allclose(t["dem_hours"], [1.0, 2.5, 0.25, 1 / 6, 0.0, 0.1])
    assert t["median_hours_per_run"].iloc[1] == pytest.approx(1.25) and np.isnan(t["median_hours_per_run"].iloc[4])
    assert t["runs"].sum() == len(runs)


def test_loo_summary_below_a_size_scores_only_the_finer_runs(fitted):
    rep = loo_scores(fitted)
    sizes = np.array(sorted({r.design.size_mm for r in fitted.training_.runs}))
    cut = float(sizes[len(sizes) // 2])
    fine = rep.summary(below_size_mm=cut)
    d = rep.per_point[rep.per_point["size_mm"] < cut]
    assert fine["n_runs"] == int((sizes < cut).sum()) > 0
    assert fine["mean_kl_velocity"] == pytest.approx(np.mean(np.r_[d["kl_primary_velocity"],
                                                                   d["kl_secondary_velocity"]]))
    assert fine["mean_kl_velocity"] != pytest.approx(rep.summary()["mean_kl_velocity"])
    none = rep.summary(below_size_mm=float(sizes[0]))  # no run is finer than the finest
    assert none["n_runs"] == 0 and np.isnan(none["mean_kl_velocity"])


def test_kl_by_sample_size_counts_every_held_out_distribution(fitted):
    t = R.kl_by_sample_size(fitted)
    n_stages = sum(len(r.stages) for r in fitted.training_.runs)
    assert t["distributions"].sum() == 2 * n_stages  # primary and secondary of every stage of every run
    assert t["share_of_total_kl"].sum() == pytest.approx(1.0, abs=1e-3)
    assert (t["kl_velocity"] >= 0).all()


@pytest.mark.parametrize("sign", [+1, -1])
def test_spearman_sign_on_made_up_data(sign):
    rng = np.random.default_rng(3)
    x = pd.Series(rng.uniform(1, 30, 40))
    y = pd.Series(sign * np.log(x) + rng.normal(0, 0.1, 40))  # HAND-MADE monotone trend plus noise
    rho, p = R.spearman(x, y)
    assert sign * rho > 0.9 and p < 1e-6
    rho0, p0 = R.spearman(x, pd.Series(rng.normal(size=40)))
    assert abs(rho0) < 0.5 and p0 > 1e-3
    assert np.isnan(R.spearman(pd.Series([1.0, 2.0, 1.0, 2.0]), pd.Series([1.0, 2.0, 3.0, 4.0]))[0])


def test_sweep_branches_agree_at_the_centre(saved):
    from msmill.surrogate.provider import SurrogateProvider

    prov = SurrogateProvider.from_file(saved)
    at = R.domain_centre(prov.surrogate)
    by_size, _ = R.sweep(prov, "size_mm", np.array([at["size_mm"]]), at)
    by_gate, samples = R.sweep(prov, "gate_deg", np.array([at["gate_deg"] - 5, at["gate_deg"]]), at, n_samples=3)
    for q in R.QUANTITIES:
        assert by_gate[q].shape == (prov.surrogate.n_stages, 2) and len(samples) == 3
        np.testing.assert_allclose(by_gate[q][:, 1], by_size[q][:, 0], rtol=1e-9)
    delta, sd = R.range_change(prov, "speed_rpm", at, "pass_through", n=4)
    ends, _ = R.sweep(prov, "speed_rpm", np.array(prov.surrogate.domain_[2]), at)
    np.testing.assert_allclose(delta, ends["pass_through"][:, 1] - ends["pass_through"][:, 0])
    assert sd.shape == delta.shape and (sd >= 0).all()


def test_run_settings_by_point_reads_each_document(campaign):
    got = R.run_settings_by_point(campaign.all_runs)
    r = campaign.slices[0]
    doc = json.loads(r.path.read_text(encoding="utf-8"))
    assert got[R.point_key(*r.statistics.design.inputs())] == doc["run"]["run_settings"]
    assert R.point_key(10.00001, 30, 1500, 40) == R.point_key(10.0, 30.0, 1500.0, 40.0)


def test_capacity_analysis_on_synthetic_points():
    pts = synthetic_points(40)
    model = CapacityModel.fit(pts)
    choked = [p for p in pts if p.outcome == "choked"]
    fs, ns, fc, nc = R.warn_counts(model, pts)
    assert (ns, nc) == (len(pts) - len(choked), len(choked)) and 0 <= fs <= ns and 0 <= fc <= nc
    loo = R.choked_loo(model, pts)
    assert [r.point for r in loo] == choked
    first = loo[0]
    assert first.capacity_tph == model.capacity_tph(first.point.size_mm, first.point.speed_rpm, first.point.gate_deg)
    without = CapacityModel.fit([q for q in pts if q is not first.point], priors=model.params.get("priors"))
    assert first.loo_capacity_tph == pytest.approx(
        without.capacity_tph(first.point.size_mm, first.point.speed_rpm, first.point.gate_deg))
    one = [p for p in pts if p.outcome == "steady"] + choked[:1]
    assert R.choked_loo(CapacityModel.fit(one), one)[0].loo_capacity_tph is None  # no other choked run
    sens = R.prior_sensitivity(pts)
    assert [s[0] for s in sens] == [v[0] for v in R.PRIOR_VARIANTS]
    assert sens[0][2] == [model.capacity_tph(*x) for x in R.CAPACITY_AT]  # shipped priors = the default fit


def test_passed_shares():
    pts = [EnvelopePoint(10, 20, 1500, 40, "steady", 18.0), EnvelopePoint(10, 40, 1500, 40, "steady", None),
           EnvelopePoint(10, 50, 1500, 10, "choked", 25.0), EnvelopePoint(10, 50, 1500, 10, "not_steady", 5.0)]
    st, ch = R.passed_shares(pts)  # HAND-MADE: a steady run without throughput is left out
    np.testing.assert_allclose(st, [0.9])
    assert ch == [0.5]
    assert R.rocks_per_s(30.0, 10.0) == pytest.approx(10 / 3.6 / 3 / (2700 * np.pi / 6 * 0.03 ** 3))
