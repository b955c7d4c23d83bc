"""Fixtures of the mill-model tests. All stage parameters here are SYNTHETIC."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))

from synthetic import synthetic_run, synthetic_table

from msmill.machine import OperatingPoint
from msmill.model import TableProvider
from msmill.psd import PSD, SizeGrid


@pytest.fixture
def grid() -> SizeGrid:
    return SizeGrid.geometric(0.038, 45.0)


@pytest.fixture
def feed(grid) -> PSD:
    return PSD.from_passing([5, 10, 20, 30, 45], [0, 10, 40, 70, 100], grid=grid)


@pytest.fixture
def op() -> OperatingPoint:
    return OperatingPoint(feed_tph=30.0, speed_rpm=1500.0, gate_deg=40.0)


@pytest.fixture
def provider() -> TableProvider:
    return TableProvider(synthetic_table(), source="SYNTHETIC table")


@pytest.fixture
def run_stats():
    return synthetic_run(10.0)
