"""Screenshot of the what-if page for ``docs/web.md`` (starts ``msmill serve``, headless Chromium).

Run: ``python scripts/web_screenshot.py [--out docs/img/web.png]``
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from playwright.sync_api import expect, sync_playwright

from msmill.web.process import serve_in_subprocess

ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("docs/img/web.png"))
    args = ap.parse_args()
    with serve_in_subprocess() as url, sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=shutil.which("chromium"), args=ARGS)
        page = browser.new_page(viewport={"width": 1100, "height": 1250})
        page.goto(url)
        expect(page.locator("#p80")).not_to_have_text("-", timeout=20_000)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(args.out), full_page=False)
        browser.close()
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
