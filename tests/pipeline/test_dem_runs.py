"""Real (short, coarse) DEM runs: the campaign executor, ingest of its folder, external import identity."""

from __future__ import annotations

import json
import warnings

import pandas as pd
import pytest

from msmill.cli.main import run as cli
from msmill.dem.mill.external import import_folder, write_external
from msmill.dem.mill.run import stats_from_dir
from msmill.errors import MsmillInputError, OutOfDomainWarning
from msmill.machine import Machine
from msmill.pipeline.campaign import design_grid, execute_run
from msmill.pipeline.store import Store
from msmill.pipeline.store.hashing import canonical_statistics
from msmill.stageparams import RunStatistics

# two stages, slow shafts, 30 mm rock, short windows (as tests/dem/test_mill_scene.py): seconds per run
MACHINE = Machine.default().model_copy(update={"n_stages": 2})
SETTINGS = {"max_time_s": 0.6, "chunk_s": 0.1, "steady_window_s": 0.1, "rel_tol": 0.5, "trend_tol": 5.0, "balance_tol": 5.0,
            "measure_s": 0.3, "snapshot_every_s": 0.005, "seed": 0}


def numbers(st: RunStatistics) -> dict:
    d = canonical_statistics(st)
    d.pop("provenance")
    return d


@pytest.fixture(scope="module")
def executed(tmp_path_factory):
    """One campaign task through the real executor, raw folder saved."""
    raw = tmp_path_factory.mktemp("raw")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        [design] = design_grid(MACHINE, [30.0], [40.0], [600.0], [40.0], bottom_speed_factor=1.0)
        task = {"machine_toml": MACHINE.to_toml(), "design": design.model_dump(), "mode": "slice",
                "run_settings": SETTINGS, "options": {"raw_dir": str(raw)}, "run_id": 7, "attempt": 1}
        out = execute_run(task)
    [folder] = raw.iterdir()
    return out, folder


def test_executor_returns_the_saved_runs_statistics(executed):
    out, folder = executed
    st = RunStatistics.from_json(out["statistics"])
    assert folder.name == "run000007-a1"
    assert numbers(st) == numbers(RunStatistics.from_json(folder / "statistics.json"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        assert numbers(stats_from_dir(folder).run) == numbers(st)
    assert out["outcome"] in ("steady", "not_steady") and out["wall_s"] > 0
    assert {f["kind"] for f in out["raw_files"]} == {"events", "removed", "timeseries", "snapshots"}


@pytest.mark.parametrize("fmt", ["csv", "parquet"])
def test_external_tables_of_our_run_give_identical_statistics(executed, tmp_path, fmt):
    _, folder = executed
    ext = write_external(folder, tmp_path / "ext", fmt=fmt, engine="test export")
    ev = pd.read_csv(ext / "events.csv") if fmt == "csv" else pd.read_parquet(ext / "events.parquet")
    assert set(ev["partner_kind"]) <= {"particle", "geometry"}  # the documented spelling, not engine codes
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        got, machine = import_folder(ext)
    assert machine == MACHINE
    assert numbers(got.run) == numbers(RunStatistics.from_json(folder / "statistics.json"))
    assert got.run.provenance["engine"] == "test export"


def test_external_import_checks_its_input(executed, tmp_path):
    _, folder = executed
    ext = write_external(folder, tmp_path / "ext")
    ev = pd.read_csv(ext / "events.csv")
    ev.drop(columns=["vn_m_s"]).to_csv(ext / "events.csv", index=False)
    with pytest.raises(MsmillInputError, match="vn_m_s"):
        import_folder(ext)
    ev.assign(partner_kind="rock").to_csv(ext / "events.csv", index=False)
    with pytest.raises(MsmillInputError, match="partner_kind"):
        import_folder(ext)


def test_cli_import_then_ingest_is_one_run(executed, tmp_path, capsys):
    _, folder = executed
    db = f"sqlite:///{tmp_path / 's.sqlite'}"
    ext = write_external(folder, tmp_path / "ext")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        assert cli(["dem", "import", str(ext), "--out", str(tmp_path / "imported")]) == 0
        assert cli(["db", "ingest", str(folder), str(tmp_path / "imported"), "--db", db,
                    "--allow-not-steady"]) == 0
    out = capsys.readouterr().out
    assert "added=1 exists=1" in out  # the imported tables are the same run as the folder
    st = Store(db)
    [rec] = st.runs()
    assert rec.source == "ingest" and rec.seed == 0 and len(st.raw_files(rec.id)) == 4
    assert cli(["db", "show", str(rec.id), "--db", db]) == 0
    assert "stage 2:" in capsys.readouterr().out
    assert cli(["db", "export", str(tmp_path / "x"), "--db", db]) == 0
    [doc] = (tmp_path / "x").iterdir()
    assert json.loads(doc.read_text())["statistics"] == canonical_statistics(st.statistics(rec.id))


def test_runs_saved_before_outcomes_are_assessed_by_todays_criterion(executed, tmp_path):
    """A run folder without a recorded outcome gets msmill.steadystate's verdict on its own time series."""
    import shutil
    import tomllib

    import tomli_w

    _, folder = executed
    old = tmp_path / "old"
    shutil.copytree(folder, old)
    settings = tomllib.loads((old / "run.toml").read_text(encoding="utf-8"))
    settings["result"].pop("outcome")
    settings["result"].pop("feed_scale")
    (old / "run.toml").write_text(tomli_w.dumps(settings), encoding="utf-8")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        st = stats_from_dir(old).run
    # 0.6 s from an empty mill with the default criterion's 0.65 s windows: never steady
    assert st.outcome == "not_steady"
    assert st.throughput_tph == pytest.approx(stats_from_dir(folder).run.throughput_tph, rel=1e-9)
