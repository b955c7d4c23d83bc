"""Per-test time limits (pytest-timeout, configured in pyproject.toml).

A broken solver or integrator should fail in seconds rather than march for
minutes. Tests without an explicit ``@pytest.mark.timeout`` get:

- ``slow``-marked tests: :data:`SLOW_TIMEOUT_S`;
- DEM tests (``tests/dem``; the first one pays the cold numba compile): the
  ini default ``timeout`` of pyproject.toml;
- everything else (core and model, pure numpy): :data:`FAST_TIMEOUT_S`.
"""

from __future__ import annotations

from pathlib import Path

import pytest

FAST_TIMEOUT_S = 60
SLOW_TIMEOUT_S = 900
_DEM = Path(__file__).parent / "dem"


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.get_closest_marker("timeout") is not None:
            continue
        if item.get_closest_marker("slow") is not None:
            item.add_marker(pytest.mark.timeout(SLOW_TIMEOUT_S))
        elif _DEM not in Path(str(item.fspath)).parents:
            item.add_marker(pytest.mark.timeout(FAST_TIMEOUT_S))
