"""``msmill report``: one self-contained HTML file that renders with its plots in headless Chromium."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from msmill.cli.main import run

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
#: ``.ci/run`` installs chromium and sets this, so a missing browser fails there instead of skipping
REQUIRED = os.environ.get("MSMILL_REQUIRE_BROWSER") == "1"


def _screenshot(html_path: Path, png: Path, profile: Path) -> None:
    """A screenshot tall enough to hold every plot of the report (its tables above them vary in height)."""
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync",
           f"--user-data-dir={profile}", "--window-size=1100,3200", "--hide-scrollbars",
           f"--screenshot={png}", html_path.as_uri()]
    subprocess.run(cmd, capture_output=True, timeout=120, check=False)


#: matplotlib's default C0 (blue), C1 (orange), C2 (green): the plots' lines and bars
PLOT_COLOURS = np.array([[31, 119, 180], [255, 127, 14], [44, 160, 44]], dtype=float)


def _coloured_pixels(png: Path) -> tuple[int, float]:
    """Pixels in the plots' colours (text and tables are grey or brown), and the overall spread."""
    from PIL import Image

    a = np.asarray(Image.open(png).convert("RGB"), dtype=float)
    d = np.linalg.norm(a[..., None, :] - PLOT_COLOURS, axis=-1).min(axis=-1)
    return int((d < 40).sum()), float(a.std())


@pytest.fixture(scope="module")
def report_file(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("report")
    out = folder / "ug2.html"
    src = (ROOT / "examples" / "ug2.toml").read_text(encoding="utf-8")  # on the single-point table
    (folder / "ug2.toml").write_text(src.replace('file = "default"', 'file = "table"', 1), encoding="utf-8")
    for csv in (ROOT / "examples").glob("*.csv"):
        (folder / csv.name).write_text(csv.read_text(encoding="utf-8"), encoding="utf-8")
    assert run(["report", str(folder / "ug2.toml"), "--out", str(out)]) == 0
    return out


def test_report_is_self_contained(report_file):
    doc = report_file.read_text(encoding="utf-8")
    assert doc.count("data:image/png;base64,") == 3
    assert not re.search(r"""(src|href)=["']?(https?:|//|file:)""", doc)  # nothing fetched from outside
    for heading in ("Headline", "Approach to steady state", "Per stage", "Power and wear", "Provenance"):
        assert heading in doc
    assert "flinger" in doc and "no-load" in doc
    # the README example rests half on statistics extrapolated in size: a warning, not only a note
    warnings_part = doc.split("<h2>Warnings</h2>", 1)[1].split("<h2>", 1)[0]
    assert "rests on stage statistics extrapolated" in warnings_part


def test_report_tables_read_as_people_read_them(report_file):
    """Issue 40 item 7: labelled columns with units (hold-up in kg as in the headline), no raw snake_case
    headers and no e-notation in the stage table, and tables that scroll rather than overflow the page."""
    doc = report_file.read_text(encoding="utf-8")
    stage_part = doc.split("<h2>Per stage</h2>", 1)[1].split("<h2>", 1)[0]
    heads = re.findall(r"<th>([^<]*)</th>", stage_part)
    assert heads[:3] == ["stage", "hold-up (kg)", "P80 (mm)"] and "flinger energy (kJ/t feed)" in heads
    assert not any("_" in h for h in heads)
    cells = re.findall(r"<td>([^<]*)</td>", stage_part)
    assert cells and not any(re.search(r"\de[+-]\d", c) for c in cells)
    assert doc.count("<div class='scroll'><table>") >= 2 and ".scroll{overflow-x:auto" in doc


@pytest.mark.skipif(CHROMIUM is None and not REQUIRED, reason="chromium not installed (.ci/run installs it)")
def test_report_renders_in_headless_chromium_with_its_plots(report_file, tmp_path):
    assert CHROMIUM is not None, "MSMILL_REQUIRE_BROWSER=1 but chromium is missing"
    shot = tmp_path / "shot.png"
    _screenshot(report_file, shot, tmp_path / "profile")
    assert shot.is_file() and shot.stat().st_size > 10_000
    coloured, spread = _coloured_pixels(shot)
    assert spread > 10  # not a blank page
    assert coloured > 3000, coloured  # the plots' coloured lines and bars are drawn
    # control: the same page with the images removed has (almost) no coloured pixels
    bare = tmp_path / "bare.html"
    bare.write_text(re.sub(r'src="data:image/png;base64,[^"]+"', 'src=""', report_file.read_text()), encoding="utf-8")
    shot2 = tmp_path / "bare.png"
    _screenshot(bare, shot2, tmp_path / "profile2")
    assert _coloured_pixels(shot2)[0] < coloured / 10
