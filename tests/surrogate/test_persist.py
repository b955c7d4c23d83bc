"""A saved surrogate is rebuilt without re-optimising and predicts bit for bit the same."""

from __future__ import annotations

import json

import numpy as np
import pytest

from msmill.errors import MsmillInputError
from msmill.surrogate import persist


def test_round_trip_is_bit_for_bit(fitted, saved):
    loaded = persist.load(saved)
    X = fitted.stage_inputs(np.geomspace(3, 40, 9), [1450.0] * 4 + [2900.0], 35.0, 30.0)
    a, sa = fitted.predict_targets(X, return_std=True)
    b, sb = loaded.predict_targets(X, return_std=True)
    assert np.array_equal(a, b, equal_nan=True)
    assert np.array_equal(sa, sb, equal_nan=True)
    assert np.array_equal(fitted.sample_targets(X, 4, rng=3), loaded.sample_targets(X, 4, rng=3), equal_nan=True)
    assert loaded.gp_.hyperparameters() == fitted.gp_.hyperparameters()


def test_document_is_versioned_with_provenance(saved, table_runs):
    doc = json.loads(saved.read_text())
    assert doc["schema_version"] == persist.SCHEMA_VERSION and doc["kind"] == persist.KIND
    prov = doc["provenance"]
    assert prov["n_runs"] == len(table_runs) and len(prov["runs_used"]) == len(table_runs)
    assert {"msmill", "numpy", "scipy", "scikit-learn"} <= set(prov["package_versions"])
    assert prov["note"] == "test"
    assert persist.is_surrogate_file(saved)


def test_bad_documents_are_one_line(saved, tmp_path):
    doc = json.loads(saved.read_text())
    for key, value, field in (("kind", "other", "kind"), ("schema_version", 99, "schema_version")):
        bad = tmp_path / f"{key}.json"
        bad.write_text(json.dumps({**doc, key: value}))
        with pytest.raises(MsmillInputError, match=field):
            persist.load(bad)
    with pytest.raises(MsmillInputError, match="existing surrogate"):
        persist.load(tmp_path / "missing.json")


def test_cached_factors_load_without_refitting_and_predict_the_same(fitted, saved, tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    first = persist.load(saved)  # refactorises and writes the cache
    cached = list((tmp_path / "cache" / "msmill" / "surrogates").glob("*.npz"))
    assert len(cached) == 1
    calls = []
    real = persist.SurrogateGP.rebuild
    monkeypatch.setattr(persist.SurrogateGP, "rebuild", classmethod(
        lambda cls, *a, **k: calls.append(1) or real.__func__(cls, *a, **k)))
    second = persist.load(saved)
    assert not calls and second.gp_.__dict__["_estimators"] is None  # read, not refitted
    X = fitted.stage_inputs(np.geomspace(3, 40, 9), [1450.0] * 4 + [2900.0], 35.0, 30.0)
    for m in (first, second):
        a, sa = fitted.predict_targets(X, return_std=True)
        b, sb = m.predict_targets(X, return_std=True)
        assert np.array_equal(a, b, equal_nan=True) and np.array_equal(sa, sb, equal_nan=True)
        assert np.array_equal(fitted.sample_targets(X, 4, rng=3), m.sample_targets(X, 4, rng=3), equal_nan=True)
    assert second.gp_.hyperparameters() == fitted.gp_.hyperparameters()
    assert np.array_equal(second.gp_.loo()[1], fitted.gp_.loo()[1])  # estimators rebuilt on demand
    cached[0].write_bytes(b"damaged")  # a damaged cache is made again, never trusted
    third = persist.load(saved)
    assert np.array_equal(third.predict_targets(X), fitted.predict_targets(X), equal_nan=True)
    assert persist.load(saved, cache=False).gp_.__dict__["_estimators"] is not None


def test_a_surrogate_of_36_levels_saves_loads_and_predicts_36_quantiles(table_runs, tmp_path):
    """The number of quantile levels travels in the file: a 36-level surrogate loads as one (and predicts the
    same), next to the shipped 28-level ones."""
    from msmill.surrogate.stage_model import StageSurrogate

    fitted = StageSurrogate(n_restarts=0, n_levels=36).fit(table_runs)
    loaded = persist.load(persist.save(fitted, tmp_path / "s36.json", {"note": "test"}))
    assert loaded.n_levels == loaded.training_.layout.n_levels == 36
    X = fitted.stage_inputs(np.geomspace(6, 30, 4), [1500.0] * 4 + [3000.0], 30.0, 40.0)
    assert np.array_equal(fitted.predict_targets(X), loaded.predict_targets(X), equal_nan=True)
    pred = loaded.decode(loaded.predict_targets(X))[0]
    assert pred.primary_quantiles_m_s.shape[-1] == 36
