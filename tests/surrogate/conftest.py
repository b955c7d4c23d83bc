"""Fixtures of the surrogate tests: one surrogate fitted once on the shipped table's DEM runs."""

from __future__ import annotations

import pytest

from msmill.model.providers import default_table_path
from msmill.stageparams import StageParameterTable


@pytest.fixture(scope="session")
def table_runs():
    return list(StageParameterTable.from_json(default_table_path()).runs)


@pytest.fixture(scope="session")
def fitted(table_runs):
    from msmill.surrogate.stage_model import StageSurrogate

    return StageSurrogate(n_restarts=0).fit(table_runs)


@pytest.fixture(scope="session")
def saved(fitted, tmp_path_factory):
    from msmill.surrogate import persist

    return persist.save(fitted, tmp_path_factory.mktemp("surrogate") / "s.json", {"note": "test"})
