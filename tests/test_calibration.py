"""Tests of msmill.calibration: recovery of known parameters, errors, CSV handling."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from msmill.calibration import calibrate, read_dropweight_csv, t10_model_pct
from msmill.errors import MsmillInputError
from msmill.ore import JK_DROP_WEIGHT_FRACTIONS_MM, get_ore

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "dropweight_synthetic.csv"
TRUE = {"A_pct": 71.8, "b_t_per_kwh": 1.67, "l_ref_mm": 20.0}


def _synthetic(seed: int, noise: float = 2.0) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    sizes = np.array([np.sqrt(a * b) for a, b in JK_DROP_WEIGHT_FRACTIONS_MM])
    size, ecs = np.meshgrid(sizes, (0.05, 0.1, 0.25, 1.0), indexing="ij")
    size, ecs = np.repeat(size.ravel(), 2), np.repeat(ecs.ravel(), 2)
    t10 = t10_model_pct(size, ecs, **TRUE) + rng.normal(0.0, noise, size.size)
    return pd.DataFrame({"size_mm": size, "ecs_kwh_t": ecs, "t10_pct": np.clip(t10, 0, 100)})


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_recovers_l_ref_within_3_sigma(seed):
    res = calibrate(_synthetic(seed), get_ore("UG2"))
    assert res.fitted == ("l_ref_mm",)
    assert abs(res.params["l_ref_mm"] - TRUE["l_ref_mm"]) < 3 * res.std_errors["l_ref_mm"]
    assert 0 < res.std_errors["l_ref_mm"] < 2.0
    assert res.r_squared > 0.95
    assert res.rmse_pct == pytest.approx(2.0, rel=0.35)  # noise sigma 2 %


@pytest.mark.parametrize("seed", [4, 5])
def test_recovers_a_and_l_ref(seed):
    res = calibrate(_synthetic(seed), get_ore("UG2"), fit=("A_pct", "l_ref_mm"))
    for k in ("A_pct", "l_ref_mm"):
        assert abs(res.params[k] - TRUE[k]) < 3 * res.std_errors[k], k


def test_recovers_a_and_b_with_l_ref_held():
    res = calibrate(_synthetic(6), get_ore("UG2"), fit=("A_pct", "b_t_per_kwh"), l_ref_mm=20.0)
    for k in ("A_pct", "b_t_per_kwh"):
        assert abs(res.params[k] - TRUE[k]) < 3 * res.std_errors[k], k
    assert res.params["l_ref_mm"] == 20.0


def test_noise_free_exact():
    res = calibrate(_synthetic(0, noise=0.0), get_ore("UG2"))
    assert res.params["l_ref_mm"] == pytest.approx(20.0, rel=1e-6)


def test_residual_table_and_to_ore():
    res = calibrate(_synthetic(7), get_ore("UG2"))
    t = res.residuals
    assert list(t.columns) == ["size_mm", "ecs_kwh_t", "t10_pct", "t10_fit_pct", "residual_pct"]
    np.testing.assert_allclose(t["residual_pct"], t["t10_pct"] - t["t10_fit_pct"])
    ore = res.to_ore(get_ore("UG2"))
    assert not ore.l_ref_is_default
    assert ore.l_ref_mm == res.params["l_ref_mm"]
    assert "msmill calibration" in ore.sources["l_ref"]


def test_example_file_is_labelled_synthetic_and_calibrates():
    assert "SYNTHETIC" in EXAMPLE.read_text().splitlines()[0]
    res = calibrate(EXAMPLE, get_ore("UG2"))
    assert abs(res.params["l_ref_mm"] - 20.0) < 3 * res.std_errors["l_ref_mm"]


def test_b_and_l_ref_not_identifiable():
    with pytest.raises(MsmillInputError, match=r"^fit.*b/L_ref"):
        calibrate(_synthetic(1), get_ore("UG2"), fit=("b_t_per_kwh", "l_ref_mm"))
    with pytest.raises(MsmillInputError, match=r"^fit"):
        calibrate(_synthetic(1), get_ore("UG2"), fit=("nonsense",))


def test_needs_held_values_without_ore():
    with pytest.raises(MsmillInputError, match=r"^A_pct"):
        calibrate(_synthetic(1), None, b_t_per_kwh=1.67)


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("size_mm,ecs_kwh_t\n1,2\n", "bad.csv.columns"),
        ("size_mm,ecs_kwh_t,t10_pct\n10,0.1,5\n-1,0.2,9\n", "bad.csv.size_mm[row 2]"),
        ("size_mm,ecs_kwh_t,t10_pct\n10,0.1,5\n10,-0.2,9\n", "bad.csv.ecs_kwh_t[row 2]"),
        ("size_mm,ecs_kwh_t,t10_pct\n10,0.1,105\n10,0.2,9\n", "bad.csv.t10_pct[row 1]"),
        ("size_mm,ecs_kwh_t,t10_pct\n10,0.1,abc\n10,0.2,9\n", "bad.csv.t10_pct[row 1]"),
        ("size_mm,ecs_kwh_t,t10_pct\n10,0.1,5\n", "bad.csv.rows"),
    ],
)
def test_bad_csv(tmp_path, text, field):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(MsmillInputError) as exc:
        read_dropweight_csv(p)
    assert str(exc.value).startswith(field), str(exc.value)
    assert "\n" not in str(exc.value)


def test_missing_and_empty_csv(tmp_path):
    with pytest.raises(MsmillInputError, match=r"^path"):
        read_dropweight_csv(tmp_path / "none.csv")
    p = tmp_path / "empty.csv"
    p.write_text("")
    with pytest.raises(MsmillInputError, match=r"^path"):
        read_dropweight_csv(p)
