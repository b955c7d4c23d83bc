"""SYNTHETIC stage parameters for the mill-model tests.

These numbers are invented for testing only (plausible magnitudes, not DEM
output). They are never shipped as a default table.
"""

from __future__ import annotations

from msmill.stageparams import RunStatistics, StageParameterTable


def synthetic_stage(i: int, n_stages: int, size_mm: float, *, hit: float = 0.5,
                    v_primary: float = 35.0, lam: float = 2.0, v_secondary: float = 8.0,
                    kick: float = 0.1, refeed: float = 0.4) -> dict:
    """One stage's statistics (SYNTHETIC)."""
    k = 0.0 if i == 1 else kick
    pt = 1.0 - k - refeed
    bottom = i == n_stages
    return {
        "stage": i,
        "kickback": k,
        "refeed": refeed,
        "pass_through": pt,
        "primary_hit_probability": hit,
        "primary_velocity": {"weights": [0.7, 0.3],
                             "means_m_s": [v_primary * (1.6 if bottom else 1.0), 0.5 * v_primary],
                             "sigmas_m_s": [0.15 * v_primary, 0.2 * v_primary]},
        "secondary_lambda": lam * (1.0 + 0.02 * size_mm),
        "secondary_velocity": {"weights": [0.6, 0.4], "means_m_s": [0.3 * v_secondary, v_secondary],
                               "sigmas_m_s": [1.0, 0.3 * v_secondary]},
    }


def synthetic_run(size_mm: float = 10.0, n_stages: int = 5, speed_rpm: float = 1500.0,
                  **stage_kw) -> RunStatistics:
    """A SYNTHETIC RunStatistics at one rock size."""
    speeds = [speed_rpm] * (n_stages - 1) + [2 * speed_rpm] if n_stages > 1 else [speed_rpm]
    return RunStatistics.from_dict({
        "design": {"size_mm": size_mm, "feed_tph": 30.0, "speed_rpm": speed_rpm, "gate_deg": 40.0,
                   "stage_speeds_rpm": speeds},
        "characteristic_time_s": 0.06,
        "stages": [synthetic_stage(i, n_stages, size_mm, **stage_kw) for i in range(1, n_stages + 1)],
        "provenance": {"note": "SYNTHETIC test fixture, not DEM output"},
    })


def synthetic_table(sizes_mm=(2.0, 8.0, 30.0), n_stages: int = 5, **stage_kw) -> StageParameterTable:
    """A SYNTHETIC StageParameterTable (refeed falls with size, as the paper describes)."""
    runs = []
    for s in sizes_mm:
        refeed = stage_kw.pop("refeed", None)
        kw = dict(stage_kw)
        kw["refeed"] = refeed if refeed is not None else max(0.15, 0.5 - 0.01 * s)
        runs.append(synthetic_run(s, n_stages, **kw))
        if refeed is not None:
            stage_kw["refeed"] = refeed
    return StageParameterTable(runs=runs, provenance={"note": "SYNTHETIC test fixture"})
