"""Slice-to-full correction: estimate from synthetic (slice, full) pairs, effect in the provider, persistence.

The "full-mill" runs here are SYNTHETIC: a shipped-table slice run with every
stage's secondary-impact count multiplied by a known factor.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from msmill.errors import OutOfDomainWarning
from msmill.surrogate import persist
from msmill.surrogate.fidelity import SliceToFullBias, match_pairs
from msmill.surrogate.provider import SurrogateProvider
from msmill.surrogate.targets import TrainingSet, honest_errors

SPEEDS = [1500.0] * 4 + [3000.0]
SIZES = np.array([6.0, 10.0, 20.0, 28.0])


def synthetic_full(run, lambda_factor: float, stream_shift: float = 0.0):
    """A synthetic full-mill run: the slice run with lambda scaled and kickback moved to refeed."""
    stages = [st.model_copy(update={"secondary_lambda": st.secondary_lambda * lambda_factor,
                                    "kickback": st.kickback - stream_shift, "refeed": st.refeed + stream_shift})
              for st in run.stages]
    return run.model_copy(update={"stages": stages, "mode": "full"})


def s_rel(run, stage: int) -> float:
    """Squared relative error of a stage's mean count as the targets carry it."""
    return (honest_errors(run)[stage]["secondary_lambda"] / run.stages[stage - 1].secondary_lambda) ** 2


@pytest.fixture(scope="module")
def layout(table_runs):
    return TrainingSet.from_runs(table_runs).layout


def test_one_pair_recovers_the_factor_with_its_own_size_as_uncertainty(table_runs, layout):
    run = table_runs[2]
    full = synthetic_full(run, 1.3)
    bias = SliceToFullBias.fit(layout, [(run, full)])
    for d, st in zip(bias.lambda_factors(layout), run.stages, strict=True):
        assert d["lambda_factor"] == pytest.approx(1.3, rel=1e-9)
        # one pair: tau^2 = d^2 - s (the part noise does not explain), var = s + 2 tau^2; s from the errors
        # the targets carry (issue 36: msmill.surrogate.targets.honest_errors) of both runs
        s = s_rel(run, st.stage) + s_rel(full, st.stage)
        assert (d["lambda_factor_sd"] / 1.3) ** 2 == pytest.approx(s + 2 * (np.log(1.3) ** 2 - s), rel=1e-6)
    streams = np.r_[[bias.offset[layout.slices(s)["streams"]] for s in range(1, 6)]]
    np.testing.assert_allclose(streams, 0.0, atol=1e-12)  # identical streams: no stream correction


def test_consistent_pairs_give_a_tight_correction_scattered_pairs_a_wide_one(table_runs, layout):
    runs = table_runs[1:4]
    same = SliceToFullBias.fit(layout, [(r, synthetic_full(r, 1.25)) for r in runs])
    spread = SliceToFullBias.fit(layout, [(r, synthetic_full(r, f)) for r, f in zip(runs, (1.05, 1.25, 1.5), strict=True)])
    i = layout.slices(3)["count"].start
    assert same.n_pairs == 3 and np.exp(same.offset[i]) == pytest.approx(1.25)
    assert np.exp(spread.offset[i]) == pytest.approx(np.exp(np.mean(np.log([1.05, 1.25, 1.5]))))
    assert spread.var[i] > 5 * same.var[i]
    # consistent pairs: only the sampling error of the mean (both runs' variances, over 3 pairs)
    # (the synthetic full run keeps the slice's standard error on a lambda f times larger)
    def s_mean(factors):
        return np.mean([s_rel(r, 3) + s_rel(synthetic_full(r, f), 3) for r, f in zip(runs, factors, strict=True)])
    s = s_mean([1.25] * 3)
    assert same.var[i] == pytest.approx(s / 3, rel=1e-6)
    # scattered pairs: plus the between-point scatter, counted for a new point (1 + 1/n)
    s = s_mean([1.05, 1.25, 1.5])
    tau2 = np.var(np.log([1.05, 1.25, 1.5]), ddof=1) - s
    assert spread.var[i] == pytest.approx(s / 3 + tau2 * 4 / 3, rel=1e-6)


def test_pairs_are_matched_by_design_point(table_runs):
    fulls = [synthetic_full(table_runs[4], 1.2)]
    pairs = match_pairs(table_runs, fulls)
    assert len(pairs) == 1 and pairs[0][0] is table_runs[4]
    other = table_runs[0].model_copy(update={"design": table_runs[0].design.model_copy(update={"feed_tph": 45.0})})
    assert match_pairs([other], [synthetic_full(table_runs[0], 1.2)]) == []


@pytest.fixture(scope="module")
def corrected(saved, table_runs, layout):
    model = persist.load(saved)
    model.slice_to_full_ = SliceToFullBias.fit(layout, [(r, synthetic_full(r, f, 0.01))
                                                        for r, f in zip(table_runs[:2], (1.2, 1.4), strict=True)])
    return model


def _params(provider, n=0):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        if n:
            return provider.sample_stage_parameters(SIZES, n, SPEEDS, 30.0, 40.0, seed=3)
        return provider.stage_parameters(SIZES, SPEEDS, 30.0, 40.0)


def test_provider_applies_the_correction_and_widens_the_band(saved, corrected):
    plain = SurrogateProvider(persist.load(saved))
    corr = SurrogateProvider(corrected)
    a, b = _params(plain), _params(corr)
    np.testing.assert_allclose(b.secondary_lambda / a.secondary_lambda, np.sqrt(1.2 * 1.4), rtol=1e-9)
    assert np.all(b.streams[..., 0] < a.streams[..., 0]) and np.all(b.streams[..., 1] > a.streams[..., 1])
    np.testing.assert_allclose(b.hit_probability, a.hit_probability, rtol=1e-12)
    assert "slice-to-full corrected, 2 pairs" in corr.source

    # same seed: the GP draws are identical, so the log-ratio of the samples is the bias draw itself,
    # one per sample and stage, shared by every size, with the correction's variance
    ratio = np.log(np.array([s.secondary_lambda for s in _params(corr, 200)])
                   / np.array([s.secondary_lambda for s in _params(plain, 200)]))  # (n, S, N)
    np.testing.assert_allclose(ratio, ratio[:, :, :1].repeat(SIZES.size, axis=2), atol=1e-9)
    bias = corrected.slice_to_full_
    lay = corrected.training_.layout
    sd = np.sqrt([bias.var[lay.slices(s)["count"].start] for s in range(1, 6)])
    np.testing.assert_allclose(ratio[:, :, 0].std(axis=0), sd, rtol=0.2)
    assert np.all(sd > 0.05)


def test_correction_survives_save_and_load(corrected, tmp_path):
    p = persist.save(corrected, tmp_path / "c.json")
    back = persist.load(p)
    np.testing.assert_array_equal(back.slice_to_full_.offset, corrected.slice_to_full_.offset)
    np.testing.assert_array_equal(back.slice_to_full_.var, corrected.slice_to_full_.var)
    a, b = _params(SurrogateProvider(corrected)), _params(SurrogateProvider(back))
    np.testing.assert_array_equal(a.secondary_lambda, b.secondary_lambda)


def test_correction_limited_to_groups(table_runs, layout):
    run = table_runs[3]
    full = synthetic_full(run, 1.4, 0.03)
    only = SliceToFullBias.fit(layout, [(run, full)], groups=("count",))
    every = SliceToFullBias.fit(layout, [(run, full)])
    for s in range(1, 6):
        sl = layout.slices(s)
        assert only.offset[sl["count"]][0] == pytest.approx(np.log(1.4))
        assert np.all(only.offset[sl["streams"]] == 0) and np.all(only.var[sl["streams"]] == 0)
        assert np.all(np.abs(every.offset[sl["streams"]]) > 0)
    back = SliceToFullBias.from_dict(only.to_dict(), layout.n_targets)
    assert back.groups == ("count",)
    with pytest.raises(Exception, match="groups"):
        SliceToFullBias.fit(layout, [(run, full)], groups=("lambda",))
