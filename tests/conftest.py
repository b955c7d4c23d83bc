"""Per-test time limits (pytest-timeout, configured in pyproject.toml).

A broken solver or integrator should fail in seconds rather than march for
minutes. Tests without an explicit ``@pytest.mark.timeout`` get:

- ``slow``-marked tests: :data:`SLOW_TIMEOUT_S`;
- the pure-numpy physics tests (core modules and ``tests/model``):
  :data:`FAST_TIMEOUT_S`;
- everything else (DEM, whose first test pays the cold numba compile;
  surrogate, store, campaign, browser tests): the ini default ``timeout`` of
  pyproject.toml.

``MSMILL_TIMEOUT_SCALE`` (environment, default 1) multiplies all three: the
mutation check (``scripts/mutation_check.py``) runs niced on a shared machine,
where a test that takes 15 s alone can take 80 s, and a time-out there would
count as a kill (or fail the baseline) for a reason that is not the mutant.

The hypothesis profile ``mutation`` (``--hypothesis-profile=mutation``, used by
the mutation check) skips shrinking: a planted bug makes property tests fail,
and shrinking their counterexamples costs minutes that tell the check nothing.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import Phase, settings

settings.register_profile("mutation", phases=[Phase.explicit, Phase.reuse, Phase.generate],
                          report_multiple_bugs=False)

FAST_TIMEOUT_S = 60
SLOW_TIMEOUT_S = 900
_HERE = Path(__file__).parent
_FAST_DIRS = (_HERE / "model",)
_FAST_FILES = {"test_breakage.py", "test_damage.py", "test_psd.py", "test_distributions.py",
               "test_ore.py", "test_calibration.py", "test_machine.py", "test_stageparams.py"}


def _is_fast(path: Path) -> bool:
    if any(d in path.parents for d in _FAST_DIRS):
        return True
    return path.parent == _HERE and path.name in _FAST_FILES


def _timeout_scale() -> float:
    raw = os.environ.get("MSMILL_TIMEOUT_SCALE", "1")
    try:
        scale = float(raw)
    except ValueError:
        raise pytest.UsageError(f"MSMILL_TIMEOUT_SCALE={raw!r}: a number >= 1") from None
    if not scale >= 1.0:
        raise pytest.UsageError(f"MSMILL_TIMEOUT_SCALE={raw!r}: a number >= 1")
    return scale


def pytest_collection_modifyitems(config, items):
    scale = _timeout_scale()
    default_s = float(config.getini("timeout") or 0)
    for item in items:
        if item.get_closest_marker("timeout") is not None:
            continue
        if item.get_closest_marker("slow") is not None:
            item.add_marker(pytest.mark.timeout(SLOW_TIMEOUT_S * scale))
        elif _is_fast(Path(str(item.fspath))):
            item.add_marker(pytest.mark.timeout(FAST_TIMEOUT_S * scale))
        elif scale != 1.0 and default_s > 0:
            item.add_marker(pytest.mark.timeout(default_s * scale))


@pytest.fixture
def own_ore_file(tmp_path):
    """Factory of a user's ore file: the packaged UG2 file under another name (HAND-MADE test values)."""
    from importlib.resources import files

    def make(name: str = "MyRock", l_ref_mm: float | None = None, folder: Path | None = None,
             fineness_ratio: float | None = None) -> Path:
        text = (files("msmill.data") / "ores" / "ug2.toml").read_text(encoding="utf-8")
        text = text.replace('name = "UG2"', f'name = "{name}"')
        if fineness_ratio is not None:
            text = text.replace("b_t_per_kwh = 1.67", f"b_t_per_kwh = 1.67\nfineness_ratio = {fineness_ratio}")
        if l_ref_mm is not None:
            text = text.replace("b_t_per_kwh = 1.67", f"b_t_per_kwh = 1.67\nl_ref_mm = {l_ref_mm}\n"
                                'l_ref_source = "HAND-MADE test value"')
        p = (folder or tmp_path) / f"{name}.toml"
        p.write_text(text, encoding="utf-8")
        return p

    return make


# ------------------------------------------------------------ a surrogate fitted once (surrogate, pipeline)
@pytest.fixture(scope="session")
def table_runs():
    """The shipped single-point table's DEM runs."""
    from msmill.model.providers import default_table_path
    from msmill.stageparams import StageParameterTable

    return list(StageParameterTable.from_json(default_table_path()).runs)


@pytest.fixture(scope="session")
def fitted(table_runs):
    from msmill.surrogate.stage_model import StageSurrogate

    return StageSurrogate(n_restarts=0).fit(table_runs)


@pytest.fixture(scope="session")
def saved(fitted, tmp_path_factory):
    from msmill.surrogate import persist

    return persist.save(fitted, tmp_path_factory.mktemp("surrogate") / "s.json", {"note": "test"})
