"""Screenshot of the what-if page for ``docs/web.md`` (starts ``msmill serve``, headless Chromium).

Run: ``python scripts/web_screenshot.py [--out docs/img/web.png]``
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

from playwright.sync_api import expect, sync_playwright

ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("docs/img/web.png"))
    args = ap.parse_args()
    proc = subprocess.Popen([sys.executable, "-m", "msmill", "serve", "--port", "0"], stdout=subprocess.PIPE,
                            text=True)
    try:
        url = re.search(r"http://[\d.]+:\d+/", proc.stdout.readline()).group(0)
        for _ in range(100):
            try:
                urllib.request.urlopen(url + "health", timeout=1)
                break
            except OSError:
                time.sleep(0.2)
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=shutil.which("chromium"), args=ARGS)
            page = browser.new_page(viewport={"width": 1100, "height": 1250})
            page.goto(url)
            expect(page.locator("#p80")).not_to_have_text("-", timeout=20_000)
            args.out.parent.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(args.out), full_page=False)
            browser.close()
    finally:
        proc.terminate()
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
