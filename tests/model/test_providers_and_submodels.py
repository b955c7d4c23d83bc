"""Stage-parameter providers and the sub-model registry (SYNTHETIC parameters)."""

from __future__ import annotations

import csv
import warnings

import numpy as np
import pytest
from synthetic import synthetic_run, synthetic_table

from msmill.errors import MsmillInputError, OutOfDomainWarning
from msmill.model import Mill, RunProvider, StageParameterProvider, TableProvider, read_simple_table
from msmill.model.submodels import DEFAULTS, SUBMODELS, resolve

pytestmark = pytest.mark.filterwarnings("ignore::msmill.errors.OutOfDomainWarning")

COLS = ["size_mm", "stage", "kickback", "refeed", "pass_through", "primary_hit_probability",
        "primary_velocity_mean_m_s", "primary_velocity_sigma_m_s", "secondary_lambda",
        "secondary_velocity_mean_m_s", "secondary_velocity_sigma_m_s"]


def simple_rows(sizes=(4.0, 16.0), n_stages=3):
    rows = []
    for size in sizes:
        for s in range(1, n_stages + 1):
            rows.append({"size_mm": size, "stage": s, "kickback": 0.0 if s == 1 else 0.1,
                         "refeed": 0.4, "pass_through": 0.6 if s == 1 else 0.5,
                         "primary_hit_probability": 0.3 + 0.01 * size,
                         "primary_velocity_mean_m_s": 30.0, "primary_velocity_sigma_m_s": 4.0,
                         "secondary_lambda": 1.5, "secondary_velocity_mean_m_s": 7.0,
                         "secondary_velocity_sigma_m_s": 2.0})
    return rows


def test_simple_toml_and_csv_tables_agree(tmp_path):
    rows = simple_rows()
    lines = ["characteristic_time_s = 0.06", "[design]", "feed_tph = 30.0", "speed_rpm = 1500.0",
             "gate_deg = 40.0", "stage_speeds_rpm = [1500.0, 1500.0, 3000.0]"]
    for r in rows:
        lines.append("[[rows]]")
        lines += [f"{k} = {v!r}" for k, v in r.items()]
    (tmp_path / "t.toml").write_text("\n".join(lines) + "\n")
    with (tmp_path / "t.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, [*COLS, "characteristic_time_s", "feed_tph", "speed_rpm", "gate_deg",
                                "stage_speed_rpm"])
        w.writeheader()
        for r in rows:
            w.writerow({**r, "characteristic_time_s": 0.06, "feed_tph": 30.0, "speed_rpm": 1500.0,
                        "gate_deg": 40.0, "stage_speed_rpm": 3000.0 if r["stage"] == 3 else 1500.0})
    a = read_simple_table(tmp_path / "t.toml")
    b = read_simple_table(tmp_path / "t.csv")
    assert a.runs == b.runs
    assert a.sizes_mm.tolist() == [4.0, 16.0]
    prov = TableProvider.from_file(tmp_path / "t.csv")
    p = prov.stage_parameters(np.array([4.0, 8.0, 16.0]))
    # interpolation in log size: 8 mm is halfway between 4 and 16
    assert p.hit_probability[0].tolist() == pytest.approx([0.34, 0.40, 0.46])


def test_simple_table_errors_name_the_field(tmp_path):
    rows = simple_rows()
    rows[2]["refeed"] = 1.4
    lines = ["characteristic_time_s = 0.06", "[design]", "feed_tph = 30.0", "speed_rpm = 1500.0",
             "gate_deg = 40.0", "stage_speeds_rpm = [1500.0, 1500.0, 3000.0]"]
    for r in rows:
        lines.append("[[rows]]")
        lines += [f"{k} = {v!r}" for k, v in r.items()]
    (tmp_path / "t.toml").write_text("\n".join(lines) + "\n")
    with pytest.raises(MsmillInputError, match=r"^t\.toml\.rows\.2\.refeed"):
        read_simple_table(tmp_path / "t.toml")


def test_json_table_and_run_providers(tmp_path):
    synthetic_table().to_json(tmp_path / "table.json")
    synthetic_run(10.0).to_json(tmp_path / "run.json")
    from msmill.model import load_provider

    t = load_provider(tmp_path / "table.json")
    r = load_provider(tmp_path / "run.json")
    assert isinstance(t, TableProvider) and isinstance(r, RunProvider)
    assert isinstance(t, StageParameterProvider) and isinstance(r, StageParameterProvider)
    p = r.stage_parameters(np.array([1.0, 10.0, 40.0]))  # one run: clamped, flagged, no warning
    assert np.allclose(p.hit_probability[:, 0], p.hit_probability[:, 2])
    assert p.extrapolated.tolist() == [True, False, True]
    # mixtures interpolate as a mixture of the neighbours: weights stay valid
    q = t.stage_parameters(np.array([5.0]))
    assert np.allclose(q.primary_velocity.weights.sum(axis=-1), 1.0)


def test_sizes_outside_the_table_do_not_warn():
    prov = TableProvider(synthetic_table(sizes_mm=(2.0, 30.0)))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        p = prov.stage_parameters(np.array([0.5, 1.0, 5.0, 50.0]))
    assert not any(issubclass(w.category, OutOfDomainWarning) for w in caught)
    assert p.extrapolated.tolist() == [True, True, False, True]


def test_unknown_submodel_name_suggests():
    with pytest.raises(MsmillInputError, match=r"model\.damage.*did you mean 'tavares'"):
        resolve("damage", "tavars", None)
    with pytest.raises(MsmillInputError, match=r"solver.*did you mean 'monte_carlo'"):
        Mill("UG2", TableProvider(synthetic_table()), solver="montecarlo")
    with pytest.raises(MsmillInputError, match="implementing TransportModel"):
        resolve("transport", object(), None)


def test_repr_lists_submodels_and_custom_model_plugs_in(feed, op):
    class HalfRefeed:
        """A custom transport sub-model: half the bulk refeed moves down."""

        name = "half_refeed"
        requires = ("streams",)

        def streams(self, params):
            s = params.streams.copy()
            s[..., 2] += 0.5 * s[..., 1]
            s[..., 1] *= 0.5
            return s

    mill = Mill("UG2", TableProvider(synthetic_table()), transport=HalfRefeed())
    text = repr(mill)
    for step in ("transport", "impacts", "breakage", "damage", "solver"):
        assert f"  {step}:" in text
    res = mill.run(feed, op)
    base = Mill("UG2", TableProvider(synthetic_table())).run(feed, op)
    assert res.submodels["transport"] == "half_refeed"
    assert res.stages["holdup_t"].sum() < base.stages["holdup_t"].sum()
    assert set(DEFAULTS) == set(SUBMODELS)


def test_result_outputs(feed, op):
    res = Mill("UG2", TableProvider(synthetic_table())).run(feed, op)
    assert res.reduction_ratio == pytest.approx(res.f80_mm / res.p80_mm)
    assert list(res.timeseries.columns) == ["time_s", "feed_tph", "holdup_t", "product_tph"]
    assert res.time_to_steady_state_s > 0
    assert res.mass_balance_error < 1e-10
    assert res.stage_psd.sum().to_numpy() == pytest.approx(np.ones(5))
    assert (res.stages["flinger_energy_j_per_t"] > 0).all()
    assert res.passing_pct.index.name == "size_mm"
    assert res.summary()["p80_mm"] == res.p80_mm


def test_lazy_top_level_exports_and_simulate(feed, op):
    import subprocess
    import sys

    code = "import sys, msmill; assert 'msmill.model' not in sys.modules; msmill.simulate; assert 'msmill.model' in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)
    from msmill import simulate

    res = simulate("UG2", feed, {"feed_tph": 30.0, "speed_rpm": 1500.0, "gate_deg": 40.0},
                   TableProvider(synthetic_table()), damage="none")
    assert res.submodels["damage"] == "none"
    assert res.p80_mm <= res.f80_mm


def test_implausible_velocities_warn(run_stats):
    from msmill.stageparams import GaussianMixture

    s0 = run_stats.stages[0].model_copy(update={
        "primary_velocity": GaussianMixture(weights=[0.9, 0.1], means_m_s=[40.0, 5000.0],
                                            sigmas_m_s=[5.0, 10.0])})
    prov = RunProvider(run_stats.model_copy(update={"stages": [s0, *run_stats.stages[1:]]}))
    with pytest.warns(OutOfDomainWarning, match="beyond 300 m/s"):
        prov.stage_parameters(np.array([10.0]))


def test_count_mixture_mean_follows_lambda_inside_and_outside_the_table() -> None:
    """The solvers use the count mixture: its mean must be the (inter/extra-polated) secondary lambda."""
    from msmill.model.providers import default_table_path, load_provider

    p = load_provider(default_table_path()).stage_parameters(np.array([1.0, 3.0, 7.0, 12.0, 25.0, 80.0]))
    assert p.secondary_count is not None and p.extrapolated.any()
    np.testing.assert_allclose(p.secondary_count.mean(), p.secondary_lambda, rtol=1e-9)
