"""Property-based fuzzing of the CLI (issue 16): any input gives exit status 0 or 2, never a
traceback, exactly one ``error:`` line on failure, and no partial output.

Three families of input: run-file contents (a valid run file with fields replaced by
arbitrary TOML values, sections dropped, or raw text), CSV contents (``psd stats``,
``ore calibrate``) and command-line arguments (``breakage table``, ``psd stats -p``,
``ore show``, ``dem run``). ``dem run`` never simulates here: ``run_mill`` is replaced by
a stub, so the test checks that every input is either rejected before the simulation
or reaches it. The resource limits are lowered while fuzzing (``msmill.validate.LIMITS``)
so that an accepted input stays cheap; examples are bounded so the file runs in seconds.
"""

from __future__ import annotations

import contextlib
import io
import math
import tempfile
from pathlib import Path

import pytest
import tomli_w
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from msmill import validate
from msmill.cli.main import run
from msmill.cli.output import MANIFEST, read_manifest

FUZZ = settings(max_examples=25, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])

#: cheap limits while fuzzing: an accepted input must still run in well under a second
SMALL_LIMITS = {"parcels_per_step": (500, "parcels"), "mc_steps": (300, "steps"),
                "parcels_total": (100_000, "parcels"), "damage_classes": (4, "damage classes"),
                "quadrature_nodes": (8, "nodes"), "grid_classes": (40, "classes")}

BASE = {
    "title": "fuzz",
    "ore": {"name": "UG2"},
    "feed": {"rate_tph": 30.0, "size_mm": [4.0, 8.0, 16.0, 32.0], "passing_pct": [10.0, 30.0, 70.0, 100.0]},
    "operating": {"speed_rpm": 1500.0, "gate_deg": 40.0},
    "model": {"damage_classes": 2, "quadrature_nodes": 4},
    "grid": {"min_mm": 0.5, "ratio": 2.0},
    "output": {"dir": "out", "csv": "p.csv", "plots": False},
}
FIELDS = [("title",), ("ore", "name"), ("ore", "l_ref_mm"), ("feed", "rate_tph"), ("feed", "size_mm"),
          ("feed", "passing_pct"), ("operating", "speed_rpm"), ("operating", "stage_speeds_rpm"),
          ("operating", "gate_deg"), ("operating", "bottom_speed_factor"), ("model", "solver"),
          ("model", "damage_classes"), ("model", "parcels_per_step"), ("model", "mc_steps"),
          ("model", "seed"), ("model", "quadrature_nodes"), ("model", "damage"), ("grid", "min_mm"),
          ("grid", "max_mm"), ("grid", "ratio"), ("output", "csv"), ("output", "dir"),
          ("output", "passing_sizes_mm"), ("machine", "file"), ("stage_parameters", "file"),
          ("feed", "rosin_rammler"), ("extra",)]
WORDS = ["", "[/bold]", "[red]x[/red]", ":smile:", "../x.csv", "a/b.csv", "x.csv", "default",
         "UG2", "monte_carlo", "expected_value", "none", "out", "\x00", "é"]
numbers_ = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10**13, 10**13),
                     st.sampled_from([0, 1, 2, 50, 1e-300, 1e300, -1.0, 0.5, 100.0]))
scalars = st.one_of(numbers_, st.booleans(), st.sampled_from(WORDS), st.text(max_size=12))
values = st.one_of(scalars, st.lists(numbers_, max_size=7), st.lists(scalars, max_size=3),
                   st.dictionaries(st.sampled_from(["a", "size_63_mm", "spread", "top_mm"]), numbers_, max_size=3))


@pytest.fixture(autouse=True)
def _small_limits(monkeypatch):
    for k, v in SMALL_LIMITS.items():
        monkeypatch.setitem(validate.LIMITS, k, v)


def cli(argv: list[str]) -> tuple[int, str, str]:
    """Run the CLI in-process; (status, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = run(argv)
    return code, out.getvalue(), err.getvalue()


def check(code: int, out: str, err: str) -> None:
    """The contract: 0 or 2, no traceback, one ``error:`` line (and nothing else on stderr
    but warnings) on failure."""
    assert code in (0, 2), (code, err)
    assert "Traceback" not in out + err
    errors = [ln for ln in err.splitlines() if ln.startswith("error:")]
    if code == 0:
        assert not errors, err
    else:
        assert len(errors) == 1, err
        assert all(ln.startswith(("error:", "warning:")) or not ln.strip() for ln in err.splitlines()), err


def check_output(folder: Path, code: int) -> None:
    """No partial output: nothing on failure; on success exactly the manifest's files."""
    if code != 0:
        assert not folder.exists(), sorted(p.name for p in folder.iterdir())
        return
    manifest = read_manifest(folder)
    assert manifest is not None
    assert sorted(p.name for p in folder.iterdir()) == sorted([*manifest["files"], MANIFEST])


def _set(doc: dict, path: tuple[str, ...], value) -> None:
    d = doc
    for key in path[:-1]:
        d = d.setdefault(key, {}) if isinstance(d.get(key, {}), dict) else {}
    d[path[-1]] = value


def _toml(doc: dict) -> str:
    try:
        return tomli_w.dumps(doc)
    except (TypeError, ValueError):  # e.g. a NUL character: write something TOML-ish by hand
        return "title = 'x'\n[feed]\nrate_tph = 30\n"


@FUZZ
@given(edits=st.lists(st.tuples(st.sampled_from(FIELDS), values), min_size=1, max_size=3),
       drop=st.lists(st.sampled_from(["ore", "feed", "operating", "model", "grid", "output"]), max_size=1))
def test_run_file_fields(edits, drop):
    doc = {k: dict(v) if isinstance(v, dict) else v for k, v in BASE.items()}
    for path, value in edits:
        _set(doc, path, value)
    for key in drop:
        doc.pop(key, None)
    with tempfile.TemporaryDirectory() as tmp:
        f = Path(tmp) / "run.toml"
        f.write_text(_toml(doc), encoding="utf-8")
        code, out, err = cli(["predict", str(f), "--out", str(Path(tmp) / "res")])
        check(code, out, err)
        check_output(Path(tmp) / "res", code)


@FUZZ
@given(raw=st.one_of(st.binary(max_size=200), st.text(max_size=200).map(str.encode)))
def test_run_file_raw_bytes(raw):
    with tempfile.TemporaryDirectory() as tmp:
        f = Path(tmp) / "run.toml"
        f.write_bytes(raw)
        code, out, err = cli(["predict", str(f), "--out", str(Path(tmp) / "res")])
        assert code == 2  # random bytes are never a valid run file
        check(code, out, err)
        check_output(Path(tmp) / "res", code)


@FUZZ
@given(raw=st.one_of(st.binary(max_size=300), st.text(max_size=300).map(str.encode)),
       suffix=st.sampled_from([".json", ".toml", ".csv", ""]))
def test_referenced_stage_parameter_file_raw_bytes(raw, suffix):
    # issue 40: a run file naming a binary (or any garbage) stage-parameter file
    doc = {k: dict(v) if isinstance(v, dict) else v for k, v in BASE.items()}
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / f"sp{suffix}").write_bytes(raw)
        doc["stage_parameters"] = {"file": f"sp{suffix}"}
        f = Path(tmp) / "run.toml"
        f.write_text(_toml(doc), encoding="utf-8")
        code, out, err = cli(["predict", str(f), "--out", str(Path(tmp) / "res")])
        assert code == 2  # random bytes are never stage parameters
        check(code, out, err)
        check_output(Path(tmp) / "res", code)


cells = st.one_of(numbers_.map(lambda v: repr(v) if isinstance(v, float) else str(v)),
                  st.sampled_from(["", "nan", "abc", "1e400", "-0", '"', "#x"]))


@FUZZ
@given(header=st.sampled_from(["size_mm,passing_pct", "size_mm,ecs_kwh_t,t10_pct", "a,b", "", "size_mm"]),
       rows=st.lists(st.lists(cells, min_size=0, max_size=4).map(",".join), max_size=8),
       command=st.sampled_from(["psd", "calibrate"]))
def test_csv_contents(header, rows, command):
    with tempfile.TemporaryDirectory() as tmp:
        f = Path(tmp) / "data.csv"
        f.write_text("\n".join([header, *rows]) + "\n", encoding="utf-8")
        argv = ["psd", "stats", str(f)] if command == "psd" else ["ore", "calibrate", str(f), "--no-residuals",
                                                                 "--out", str(Path(tmp) / "ore.toml")]
        code, out, err = cli(argv)
        check(code, out, err)
        if code != 0:
            assert not (Path(tmp) / "ore.toml").exists()


opt_values = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr),
                       st.integers(-10**9, 10**9).map(str), st.sampled_from(["abc", "", "-1", "1e309", "[b]"]))


@FUZZ
@given(opts=st.dictionaries(st.sampled_from(["--size-mm", "--velocity", "--damage", "--grid-min-mm",
                                             "--grid-max-mm", "--ore"]), opt_values, max_size=3))
def test_breakage_table_arguments(opts):
    argv = ["breakage", "table"]
    for k, v in opts.items():
        argv += [k, v]
    check(*cli(argv))


@FUZZ
@given(name=st.one_of(st.sampled_from(WORDS), st.text(max_size=15)))
def test_ore_show_names(name):
    check(*cli(["ore", "show", name]))


#: Exit status of the stub of run_mill: validation let the input through to the simulation.
REACHED = 99


@FUZZ
@given(opts=st.dictionaries(st.sampled_from(["--size-mm", "--feed-tph", "--speed-rpm", "--bottom-factor",
                                             "--gate-deg", "--max-time-s", "--measure-s", "--seed"]),
                            opt_values, max_size=3))
def test_dem_run_arguments_checked_before_simulation(opts, monkeypatch):
    import typer

    import msmill.dem.mill.run as dem_run

    def stub(*args, **kwargs):
        raise typer.Exit(REACHED)

    monkeypatch.setattr(dem_run, "run_mill", stub)
    argv = ["dem", "run", "default", "--no-progress"]
    opts.setdefault("--size-mm", "20")
    with tempfile.TemporaryDirectory() as tmp:
        for k, v in opts.items():
            argv += [k, v]
        argv += ["--out", str(Path(tmp) / "dem")]
        code, out, err = cli(argv)
        assert not (Path(tmp) / "dem").exists()  # nothing written before (or instead of) the run
        if code == REACHED:  # accepted: then every value must have been a sensible one
            size = float(opts["--size-mm"])
            assert math.isfinite(size) and 0 < size < 70
            assert "error:" not in err
            return
        assert code == 2
        check(code, out, err)


def test_fuzz_contract_can_fail():
    """The checker itself rejects a traceback, two error lines and a stray file (planted faults)."""
    with pytest.raises(AssertionError):
        check(1, "", "Traceback (most recent call last):\n")
    with pytest.raises(AssertionError):
        check(2, "", "error: a\nerror: b\n")
    with tempfile.TemporaryDirectory() as tmp, pytest.raises(AssertionError):
        (Path(tmp) / "res").mkdir()
        (Path(tmp) / "res" / "half.csv").write_text("x")
        check_output(Path(tmp) / "res", 2)


# ---------------------------------------------------------------- issue 40: store, campaign, sweep, web API
#: 40 + 40 + 35 + 40 = 155 cases of the issue's new classes
FUZZ40 = settings(FUZZ, max_examples=40)
FUZZ35 = settings(FUZZ, max_examples=35)
class _Reached(Exception):
    """The command got past its checks to the (stubbed) computation."""


STORE_WORDS = ["", "sqlite:///", "sqlite:////nonexistent/x.sqlite", "postgresql://u:p@127.0.0.1:1/x", "foo://bar",
               "/", ".", "x.sqlite", "a b", "\x00", ":memory:", "sqlite:///:memory:", "mysql://x"]


@FUZZ40
@given(db=st.one_of(st.sampled_from(STORE_WORDS), st.text(max_size=20)),
       cmd=st.sampled_from([["db", "info"], ["db", "list"], ["db", "show", "1"], ["campaign", "status", "c"]]),
       size=st.one_of(st.none(), st.sampled_from(["40:20", "20:40", "x", ":", "1e400:2", "nan:1"])))
def test_store_urls_and_ranges(db, cmd, size):
    with tempfile.TemporaryDirectory() as tmp:
        db_arg = db.replace("x.sqlite", str(Path(tmp) / "x.sqlite"))
        extra = ["--size-mm", size] if size is not None and cmd[1] == "list" else []
        code, out, err = cli([*cmd, "--db", db_arg, *extra])
        check(code, out, err)
        assert not any(Path(tmp).iterdir())  # a read never creates a store


@FUZZ40
@given(name=st.one_of(st.sampled_from(WORDS), st.text(max_size=12)),
       ore=st.one_of(st.none(), st.sampled_from(WORDS)),
       sets=st.lists(st.tuples(st.sampled_from(["max_time_s", "measure_s", "seed", "start", "adaptive", "chunk_s",
                                                "checkpoint_every_s", "nonsense"]),
                               st.one_of(st.sampled_from(["-5", "0", "nan", "inf", "1e9", "true", "table", "x"]),
                                         st.integers(-5, 10).map(str))), max_size=2))
def test_campaign_create_arguments(name, ore, sets):
    with tempfile.TemporaryDirectory() as tmp:
        args = ["campaign", "create", name, "--db", str(Path(tmp) / "s.sqlite"),
                "--checkpoint-dir", str(Path(tmp) / "ck")]
        args += ["--ore", ore] if ore is not None else []
        for k, v in sets:
            args += ["--set", f"{k}={v}"]
        check(*cli(args))


@FUZZ35
@given(cmd=st.sampled_from(["sweep", "optimize"]),
       var=st.lists(st.one_of(st.sampled_from(["speed_rpm=1200:1900:8", "speed_rpm=1900:1200", "feed_tph=10:60:0",
                                               "gate_deg=40,60", "x=1:2", "speed_rpm=", "feed_tph=1e9:1e10:1000000",
                                               "feed_scale=0.5:2:3"]), st.text(max_size=10)),
                    min_size=1, max_size=3),
       n_grid=st.one_of(st.none(), st.sampled_from(["0", "-1", "1000000", "x", "3"])),
       target=st.one_of(st.none(), st.sampled_from(["--target-p80-mm=-3", "--target-p80-mm=nan",
                                                   "--target-passing=2:150", "--target-passing=x",
                                                   "--target-p80-mm=16"])))
def test_sweep_and_optimize_arguments(cmd, var, n_grid, target, monkeypatch):
    from msmill.model import operating

    def stub(*a, **k):
        raise _Reached

    monkeypatch.setattr(operating, "sweep", stub)
    monkeypatch.setattr(operating, "optimize", stub)
    flag = "--var" if cmd == "sweep" else "--bound"
    args = [cmd, str(Path(__file__).parents[1] / "examples" / "ug2.toml"), "--out", "unused"]
    for v in var:
        args += [flag, v]
    if cmd == "optimize":
        args += [] if n_grid is None else ["--n-grid", n_grid]
        args += [] if target is None else [target]
    try:
        code, out, err = cli(args)
    except _Reached:
        return  # every check passed: the computation was reached
    check(code, out, err)


@pytest.fixture(scope="module")
def web_client():
    import warnings

    pytest.importorskip("fastapi")
    from fastapi.testclient import TestClient

    from msmill.web.app import create_app

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return TestClient(create_app(max_request_bytes=200_000))


WEB_BASE = {"title": "fuzz", "ore": {"name": "UG2"},
            "feed": {"rate_tph": 30.0, "size_mm": [4.0, 8.0, 16.0, 32.0], "passing_pct": [10.0, 30.0, 70.0, 100.0]},
            "operating": {"speed_rpm": 1500.0, "gate_deg": 40.0}, "output": {"plots": False},
            "model": {"damage_classes": 2, "quadrature_nodes": 4}, "grid": {"min_mm": 0.5, "ratio": 2.0},
            "stage_parameters": {"file": "table"}}
WEB_FIELDS = [("ore", "name"), ("feed", "rate_tph"), ("feed", "size_mm"), ("feed", "passing_pct"),
              ("operating", "speed_rpm"), ("operating", "gate_deg"), ("model", "solver"), ("grid", "ratio"),
              ("attachments", "feed_csv"), ("attachments", "ore_toml"), ("attachments", "secret"),
              ("stage_parameters", "file"), ("machine", "file"), ("extra",)]


@FUZZ40
@given(edits=st.lists(st.tuples(st.sampled_from(WEB_FIELDS), st.one_of(values, st.sampled_from(
    ["size_mm,passing_pct\n1,5\n8,45\n16,100\n", "\x00\x01", "[ore]\nname = 'x'", "../../etc/passwd"]))),
    min_size=1, max_size=3),
    raw=st.one_of(st.none(), st.binary(max_size=60)))
def test_web_api_bodies(web_client, edits, raw):
    import json

    if raw is not None:
        r = web_client.post("/predict", content=raw, headers={"content-type": "application/json"})
    else:
        doc = json.loads(json.dumps(WEB_BASE))
        for path, value in edits:
            _set(doc, path, value)
        try:
            body = json.dumps(doc, allow_nan=True)
        except (TypeError, ValueError):
            return
        r = web_client.post("/predict", content=body.encode(), headers={"content-type": "application/json"})
    assert r.status_code in (200, 413, 422), (r.status_code, r.text[:300])
    if r.status_code == 422:
        d = r.json()["detail"]
        assert set(d) == {"field", "value", "allowed", "message"} and "\n" not in d["message"]
        assert "Traceback" not in r.text and "internal error" not in r.text
