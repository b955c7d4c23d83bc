"""``msmill serve`` in a child process, for scripts and tests that drive the page in a browser."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def serve_in_subprocess(startup_s: float = 20.0, env: dict[str, str] | None = None) -> Iterator[str]:
    """Start ``msmill serve --port 0``, wait until ``/health`` answers, yield its base URL, stop it.

    ``env``: variables set for the server on top of this process's environment (e.g. ``TMPDIR``).

    Raises
    ------
    RuntimeError
        If the server does not print its address or does not answer within ``startup_s``.
    """
    proc = subprocess.Popen([sys.executable, "-m", "msmill", "serve", "--port", "0"], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env={**os.environ, **(env or {})})
    try:
        m, line = None, ""
        for _ in range(20):  # "warming ..." first, then the ready line with the address
            line = proc.stdout.readline()
            m = re.search(r"http://[\d.]+:\d+/", line)
            if m or not line:
                break
        if not m:
            raise RuntimeError(f"msmill serve did not start: {line!r}")
        url = m.group(0)
        deadline = time.monotonic() + startup_s
        while True:
            try:
                urllib.request.urlopen(url + "health", timeout=1)
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"msmill serve at {url} did not answer within {startup_s:g} s") from None
                time.sleep(0.2)
        yield url
    finally:
        proc.terminate()
        proc.wait(timeout=10)
