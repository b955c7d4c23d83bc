"""The what-if page in a real headless Chromium: sliders, upload, a bad input, a screenshot.

Starts ``msmill serve`` as a subprocess on a free port and drives the page with
Playwright using the system Chromium (Debian's ``chromium``; ``.ci/run``
installs it and sets ``MSMILL_REQUIRE_BROWSER=1`` so a missing browser fails
there instead of skipping).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
REQUIRED = os.environ.get("MSMILL_REQUIRE_BROWSER") == "1"
if CHROMIUM is None or not __import__("importlib").util.find_spec("playwright"):
    if REQUIRED:
        raise RuntimeError("MSMILL_REQUIRE_BROWSER=1 but chromium or playwright is missing")
    pytest.skip("chromium or playwright not installed", allow_module_level=True)

from playwright.sync_api import expect, sync_playwright  # noqa: E402

from msmill.web.process import serve_in_subprocess  # noqa: E402

ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]


@pytest.fixture(scope="module")
def server():
    with serve_in_subprocess() as url:
        yield url


def _changes(page, selector: str, old: str, timeout_ms: int = 15_000) -> str:
    expect(page.locator(selector)).not_to_have_text(old, timeout=timeout_ms)
    return page.locator(selector).inner_text()


def test_page_what_if(server: str, tmp_path: Path) -> None:
    feed_csv = tmp_path / "feed.csv"
    feed_csv.write_text("size_mm,passing_pct\n1,5\n4,20\n8,45\n16,80\n22.4,100\n", encoding="utf-8")
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        page = browser.new_page(viewport={"width": 1100, "height": 1300})
        page.goto(server)
        p80 = _changes(page, "#p80", "-")
        # the README example rests half on statistics extrapolated in size: the page says so among its warnings
        expect(page.locator("#warnings")).to_contain_text("rests on stage statistics extrapolated")
        # ... and its PSD plot shades those size classes, with a legend line
        assert page.locator("#psd_plot .extrapolated_span").count() >= 1
        expect(page.locator("#extrapolated_legend")).to_have_text("stage statistics extrapolated in size")
        assert float(page.locator("#psd_plot .extrapolated_span").first.get_attribute("width")) > 10
        product = page.locator("#product_line").get_attribute("d")
        holdup = page.locator("#holdup").inner_text()

        page.locator("#feed_rate").fill("50")  # more feed: more rock held in the mill
        holdup2 = _changes(page, "#holdup", holdup)
        assert float(holdup2) > float(holdup)
        p80 = page.locator("#p80").inner_text()  # the feed rate moves P80 too (shipped surrogate)
        product = page.locator("#product_line").get_attribute("d")

        page.locator("#speed").fill("1850")  # faster rotors: finer product, new curve
        p80_fast = _changes(page, "#p80", p80)
        assert float(p80_fast) < float(p80)
        assert page.locator("#product_line").get_attribute("d") != product

        page.locator("#feed_file").set_input_files(str(feed_csv))  # a finer feed: finer product
        p80_fine = _changes(page, "#p80", p80_fast)
        assert float(p80_fine) < float(p80_fast)

        page.locator("#gate").fill("120")  # beyond the allowed 0-90 deg
        expect(page.locator("#error")).to_contain_text("operating.gate_deg", timeout=15_000)
        expect(page.locator("#error")).to_contain_text("90")
        page.locator("#gate").fill("40")
        expect(page.locator("#error")).to_have_text("", timeout=15_000)

        shot = tmp_path / "page.png"
        page.screenshot(path=str(shot), full_page=True)
        browser.close()
    from PIL import Image

    img = np.asarray(Image.open(shot).convert("L"), dtype=float)
    assert img.shape[0] > 500 and img.std() > 10  # not blank
    plot = img[150:450, 380:1000]  # the PSD plot area holds drawn lines, not only background
    assert (plot < 200).mean() > 0.01


def test_api_docs_render_with_the_network_off(server: str) -> None:
    # every request that leaves this machine is refused: Swagger UI must come from msmill's own server
    outside: list[str] = []
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        page = browser.new_page()

        def route(r):
            if r.request.url.startswith(server):
                return r.continue_()
            outside.append(r.request.url)
            return r.abort()

        page.route("**/*", route)
        page.goto(server + "docs")
        expect(page.locator(".swagger-ui .info .title")).to_contain_text("msmill", timeout=15_000)
        expect(page.locator(".opblock-summary-path", has_text="/predict")).to_be_visible()
        browser.close()
    assert outside == []
