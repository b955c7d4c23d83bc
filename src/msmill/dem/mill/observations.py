"""The paper's three observations on its machine as statistical statements about DEM runs (issue 37).

Placeholder: filled in below.
"""

from __future__ import annotations

#: rotation-sense configurations of the study, in the order they are run and reported
CONFIGS: tuple[str, ...] = ("down_down", "up_up", "down_up", "up_down", "co_rotating")


def run_dir_name(size_mm: float, speed_rpm: float, seed: int) -> str:
    """Folder name of one run's export: ``<size>mm_<rpm>rpm_seed<k>``."""
    return f"{size_mm:g}mm_{speed_rpm:g}rpm_seed{seed}"
