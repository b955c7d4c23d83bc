"""HTTP API of ``msmill serve``: same numbers as ``msmill predict``, clean 422s, size limits."""

from __future__ import annotations

import tomllib
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("fastapi")
from fastapi.testclient import TestClient

from msmill.cli.main import run as cli_run
from msmill.web.app import create_app

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "ug2.toml"


@pytest.fixture(scope="module")
def client() -> TestClient:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return TestClient(create_app(max_request_bytes=200_000))


def _example() -> dict:
    data = tomllib.loads(EXAMPLE.read_text(encoding="utf-8"))
    data.pop("output")
    data["output"] = {"plots": False}
    return data


def test_health_ores_openapi(client: TestClient) -> None:
    assert client.get("/health").json()["status"] == "ok"
    names = [o["name"] for o in client.get("/ores").json()]
    assert {"UG2", "Platreef"} <= set(names)
    spec = client.get("/openapi.json").json()
    assert {"/predict", "/ores", "/health"} <= set(spec["paths"])


def test_predict_reproduces_cli(client: TestClient, tmp_path: Path) -> None:
    out = tmp_path / "cli"
    assert cli_run(["predict", str(EXAMPLE), "--out", str(out), "--no-plots"]) == 0
    cli = pd.read_csv(out / "ug2_product.csv")
    r = client.post("/predict", json=_example())
    assert r.status_code == 200, r.text
    api = pd.DataFrame(r.json()["psd"])
    np.testing.assert_allclose(api["product_passing_pct"], cli["product_passing_pct"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(api["upper_mm"], cli["upper_mm"], rtol=1e-12)
    cli_stages = pd.read_csv(out / "ug2_product_stages.csv")
    np.testing.assert_allclose(pd.DataFrame(r.json()["stages"])["holdup_t"], cli_stages["holdup_t"], atol=1e-12)


def test_run_file_download_reproduces_request(client: TestClient, tmp_path: Path) -> None:
    req = _example()
    req["operating"]["speed_rpm"] = 1650.0
    body = client.post("/predict", json=req).json()
    p = tmp_path / "again.toml"
    p.write_text(body["run_file_toml"], encoding="utf-8")
    assert cli_run(["predict", str(p), "--out", str(tmp_path / "o"), "--no-plots"]) == 0
    again = pd.read_csv(next((tmp_path / "o").glob("*.csv")))
    np.testing.assert_allclose(again["product_passing_pct"], pd.DataFrame(body["psd"])["product_passing_pct"],
                               atol=1e-9)


def test_speed_changes_product(client: TestClient) -> None:
    req = _example()
    a = client.post("/predict", json=req).json()["summary"]["p80_mm"]
    req["operating"]["speed_rpm"] = 1850.0
    b = client.post("/predict", json=req).json()["summary"]["p80_mm"]
    assert b < a  # faster rotors, harder impacts, finer product


@pytest.mark.parametrize(("path", "value", "field"), [
    (("feed", "rate_tph"), -3, "request.feed.rate_tph"),
    (("operating", "gate_deg"), 120, "request.operating.gate_deg"),
    (("ore", "name"), "UG3", "request.ore.name"),
    (("model", "solver"), "magic", "request.model.solver"),
    (("stage_parameters", "file"), "/etc/passwd", "request.stage_parameters.file"),
    (("feed", "passing_pct"), "lots", "request.feed.passing_pct"),
])
def test_bad_request_names_field(client: TestClient, path: tuple[str, str], value: object, field: str) -> None:
    req = _example()
    req.setdefault(path[0], {})[path[1]] = value
    r = client.post("/predict", json=req)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert detail["field"].startswith(field), detail
    assert detail["message"].startswith(field)


def test_malformed_and_oversized(client: TestClient) -> None:
    r = client.post("/predict", content=b'{"ore": ', headers={"content-type": "application/json"})
    assert r.status_code == 422 and r.json()["detail"]["field"] == "request"
    big = b'{"title": "' + b"x" * 300_000 + b'"}'
    r = client.post("/predict", content=big, headers={"content-type": "application/json"})
    assert r.status_code == 413


def test_attachments(client: TestClient) -> None:
    req = _example()
    req["attachments"] = {"feed_csv": "size_mm,passing_pct\n1,5\n4,20\n8,45\n16,80\n22.4,100\n"}
    r = client.post("/predict", json=req)
    assert r.status_code == 200, r.text
    assert r.json()["summary"]["f80_mm"] == pytest.approx(16.0, rel=0.03)  # the uploaded feed's 80 % size
    ore_text = (ROOT / "src" / "msmill" / "data" / "ores" / "ug2.toml").read_text(encoding="utf-8")
    req = _example()
    req["attachments"] = {"ore_toml": ore_text.replace("71.8", "50.0")}
    softer = client.post("/predict", json=req).json()["summary"]
    base = client.post("/predict", json=_example()).json()["summary"]
    # smaller A: less fines per breakage, a coarser product. P50 sits where t10 acts; P80 (20 mm, set by the
    # coarse classes' breakage probability) may not move between two grid points
    assert softer["p50_mm"] > base["p50_mm"] and softer["p80_mm"] >= base["p80_mm"]
    req["attachments"] = {"feed_csv": "size_mm,passing_pct\n1,50\n2,40\n"}
    r = client.post("/predict", json=req)
    assert r.status_code == 422 and "feed_csv" in r.json()["detail"]["field"]
    req["attachments"] = {"secret_file": "x"}
    assert client.post("/predict", json=req).status_code == 422


def test_requests_leave_no_temporary_files(client: TestClient, tmp_path: Path, monkeypatch) -> None:
    # every request's attachment folder goes with it, after a success and after a refused request
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    ore_text = (ROOT / "src" / "msmill" / "data" / "ores" / "ug2.toml").read_text(encoding="utf-8")
    ok = _example()
    ok["attachments"] = {"ore_toml": ore_text, "feed_csv": "size_mm,passing_pct\n1,5\n4,20\n8,45\n16,80\n22.4,100\n"}
    bad = _example()
    bad["attachments"] = {"ore_toml": "not = [toml"}
    for _ in range(3):
        assert client.post("/predict", json=ok).status_code == 200
        assert client.post("/predict", json=bad).status_code == 422
    assert list(tmp_path.iterdir()) == []


def test_served_app_leaves_no_file_after_50_requests(tmp_path: Path) -> None:
    """``python -m msmill serve`` (a real server process, its TMPDIR a fresh folder), then 50 POST /predict, half of
    them refused: nothing new in the temporary folder."""
    import json
    import urllib.error
    import urllib.request

    from msmill.web.process import serve_in_subprocess

    ore_text = (ROOT / "src" / "msmill" / "data" / "ores" / "ug2.toml").read_text(encoding="utf-8")
    ok, bad = _example(), _example()
    ok["attachments"] = {"ore_toml": ore_text, "feed_csv": "size_mm,passing_pct\n1,5\n4,20\n8,45\n16,80\n22.4,100\n"}
    bad["attachments"] = {"ore_toml": "not = [toml"}
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    with serve_in_subprocess(startup_s=60.0, env={"TMPDIR": str(tmp)}) as url:
        before = sorted(tmp.rglob("*"))
        codes = []
        for i in range(50):
            req = urllib.request.Request(url + "predict", data=json.dumps(ok if i % 2 else bad).encode(),
                                         headers={"Content-Type": "application/json"})
            try:
                with urllib.request.urlopen(req, timeout=60) as r:
                    codes.append(r.status)
            except urllib.error.HTTPError as e:
                codes.append(e.code)
        after = sorted(tmp.rglob("*"))
    assert codes.count(200) == 25 and codes.count(422) == 25
    assert after == before


def test_predict_psd_rows_flag_the_extrapolated_and_thin_classes(client: TestClient) -> None:
    """The page shades what the JSON flags: the README example's extrapolated classes, per PSD row."""
    from msmill.model.runfile import RunFile

    r = client.post("/predict", json=_example())
    rows = pd.DataFrame(r.json()["psd"])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rf = RunFile.from_toml(EXAMPLE)
        mill, feed, op = rf.build()
        res = mill.run(feed, op, timeseries=False)
    np.testing.assert_array_equal(rows["extrapolated"], res.extrapolated_classes)
    np.testing.assert_array_equal(rows["thin_data"], res.thin_data_classes)
    assert 0 < rows["extrapolated"].sum() < len(rows)  # the fine classes and the top class, not all


def test_a_warmed_service_answers_its_first_request_from_the_built_mill(monkeypatch) -> None:
    from msmill.model.runfile import RunFile
    from msmill.web.service import PredictionService, default_request

    svc = PredictionService()
    assert svc.warm() > 0 and len(svc._cache) == 1

    def no_build(self):
        raise AssertionError("the first request built a mill again")

    monkeypatch.setattr(RunFile, "build", no_build)
    req = default_request()
    req["feed"]["rate_tph"] = 45.0  # another operating point: the mill (provider, ore, grid) is reused
    assert svc.predict(req)["summary"]["feed_tph"] == 45.0


def test_docs_are_served_from_the_install(client: TestClient) -> None:
    import re

    page = client.get("/docs")
    assert page.status_code == 200
    refs = re.findall(r'(?:src|href)="([^"]+)"', page.text)
    assert refs and all(r.startswith("/") for r in refs), refs  # nothing from a CDN
    for r in refs:
        assert client.get(r).status_code == 200, r


def test_openapi_describes_the_request_and_the_error_body_returned(client: TestClient) -> None:
    from msmill.web.app import ErrorBody

    doc = client.get("/openapi.json").json()
    post = doc["paths"]["/predict"]["post"]
    props = post["requestBody"]["content"]["application/json"]["schema"]["properties"]
    assert {"ore", "feed", "operating", "attachments"} <= set(props)  # not an empty object
    assert post["responses"]["422"]["content"]["application/json"]["schema"]["$ref"].endswith("/ErrorBody")
    refs: set[str] = set()

    def walk(x):
        if isinstance(x, dict):
            refs.update(v for k, v in x.items() if k == "$ref")
            for k, v in x.items():
                if k != "$ref":
                    walk(v)
        elif isinstance(x, list):
            for v in x:
                walk(v)

    walk(doc)
    assert refs and all(r.split("/")[-1] in doc["components"]["schemas"] for r in refs)
    bad = _example()
    bad["operating"]["gate_deg"] = 120
    r = client.post("/predict", json=bad)
    assert r.status_code == 422
    assert ErrorBody.model_validate(r.json()).detail.field.endswith("operating.gate_deg")  # the body the schema names


def test_rotation_sense_is_offered_and_a_sense_without_a_surrogate_says_so(client: TestClient) -> None:
    """Issue 37: the page lists the rotation senses (GET /rotation-senses); a request for a sense whose
    surrogate is not shipped yet is a 422 whose one line names the field and the sense."""
    senses = client.get("/rotation-senses").json()
    assert [s["name"] for s in senses if s["default"]] == ["down_down"]
    assert {s["name"] for s in senses} >= {"down_down", "up_up"}
    assert next(s for s in senses if s["name"] == "down_down")["surrogate_shipped"]
    req = _example()
    req["machine"] = {"rotation_sense": "up_up"}
    r = client.post("/predict", json=req)
    shipped = next(s for s in senses if s["name"] == "up_up")["surrogate_shipped"]
    if shipped:
        assert r.status_code == 200, r.text
    else:
        assert r.status_code == 422
        d = r.json()["detail"]
        assert d["field"].endswith("stage_parameters.file") and "rotation sense 'up_up'" in d["message"]
    req["machine"] = {"rotation_sense": "down_down"}
    assert client.post("/predict", json=req).status_code == 200
