"""Benchmark: speed as a user feels it -- whole commands as processes on the shipped examples (issue 39).

Each command runs ``--repeats`` times as a fresh process (``python -m msmill ...``, outputs to a
temporary folder); reported are the median wall time and the median CPU time of the process and its
children (``resource.getrusage``). The commands, taking turns round by round so that a busy machine
slows them alike:

* ``predict``: ``msmill predict examples/ug2.toml``;
* ``ore_list``: ``msmill ore list``;
* ``report``: ``msmill report examples/ug2.toml``;
* ``sweep``: ``msmill sweep examples/ug2.toml --var speed_rpm=1200:1900:8 --var gate_deg=40,60`` (16
  points; reported per point);
* ``optimize``: the first ``msmill optimize`` of ``docs/validation.md``;
* ``score``: ``msmill surrogate score default`` (skipped with ``--skip-score``);
* ``web_first``: ``msmill serve`` started, the first ``POST /predict`` timed (wall) once the server
  answers ``/health`` or ``/``.

The first round warms the user's caches (a loaded surrogate's factorisations, numba's cache, Python's
bytecode cache) and is not counted. The processes run without ``PYTHONDONTWRITEBYTECODE`` (set in some
sandboxes, never by a user's shell): ``pip install`` writes the bytecode of the installed files, and an
editable install writes it on the first run, so a user's later commands do not compile the package again.
A ``floor`` line gives the CPU time of a Python process that only imports the libraries ``predict``
uses (numpy, scipy.sparse.linalg, pandas, matplotlib's Agg figure, typer, rich): what no change inside
msmill can take away. Last line (CPU seconds of the whole process; ``web_first_s`` the request's wall time):
``predict_s=<a> ore_list_s=<b> report_s=<c> sweep_per_point_s=<d> optimize_s=<e> score_s=<f>
web_first_s=<g>``.

Run: ``python benchmarks/user_speed.py [--repeats 3] [--only predict ore_list]``
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
UG2 = str(ROOT / "examples" / "ug2.toml")


def commands(out: Path) -> dict[str, list[str]]:
    """Command lines per benchmark key."""
    return {
        "predict": ["predict", UG2, "--out", str(out / "predict")],
        "ore_list": ["ore", "list"],
        "report": ["report", UG2, "--out", str(out / "report.html")],
        "sweep": ["sweep", UG2, "--var", "speed_rpm=1200:1900:8", "--var", "gate_deg=40,60", "--out",
                  str(out / "sweep")],
        "optimize": ["optimize", UG2, "--bound", "speed_rpm=1200:1900", "--goal", "min_energy",
                     "--target-p80-mm", "16", "--l-ref-se-mm", "1.2", "--out", str(out / "optimize")],
        "score": ["surrogate", "score", "default"],
    }


#: the third-party imports of ``msmill predict`` (the floor line)
FLOOR_IMPORTS = ("numpy, scipy.sparse.linalg, pandas, matplotlib.figure, matplotlib.backends.backend_agg, typer, "
                 "rich.table")
#: a user's environment: Python writes its bytecode cache (module docstring)
ENV = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}


def run_timed(args: list[str], python_args: list[str] | None = None) -> tuple[float, float, int]:
    """Wall and CPU time (s) of one ``python -m msmill ARGS`` process (or ``python PYTHON_ARGS``), and its
    exit status."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    cmd = [sys.executable, *python_args] if python_args is not None else [sys.executable, "-m", "msmill", *args]
    p = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=ROOT, env=ENV, check=False)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, p.returncode


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def web_first_request() -> float:
    """Wall time (s) of the first POST /predict after ``msmill serve`` answers."""
    port = free_port()
    srv = subprocess.Popen([sys.executable, "-m", "msmill", "serve", "--port", str(port)],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=ROOT, env=ENV)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                with urllib.request.urlopen(base + "/defaults", timeout=5) as r:
                    body = r.read()
                break
            except OSError:
                if time.monotonic() > deadline or srv.poll() is not None:
                    raise RuntimeError("msmill serve did not come up") from None
                time.sleep(0.1)
        req = urllib.request.Request(base + "/predict", data=body, headers={"Content-Type": "application/json"})
        t0 = time.perf_counter()
        with urllib.request.urlopen(req, timeout=300) as r:
            json.loads(r.read())
        return time.perf_counter() - t0
    finally:
        srv.terminate()
        srv.wait(timeout=30)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--only", nargs="+", default=None)
    ap.add_argument("--skip-score", action="store_true")
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        cmds = commands(Path(tmp))
        keys = [k for k in cmds if (a.only is None or k in a.only) and not (a.skip_score and k == "score")]
        res: dict[str, list[tuple[float, float]]] = {k: [] for k in keys}
        floor = []
        for rnd in range(a.repeats + 1):
            for k in keys:
                wall, cpu, code = run_timed(cmds[k])
                if code not in (0,):
                    print(f"{k}: exit {code} ({' '.join(cmds[k])})")
                if rnd:  # round 0 warms the caches
                    res[k].append((wall, cpu))
            if rnd:
                floor.append(run_timed([], ["-c", f"import {FLOOR_IMPORTS}"])[1])
        web = []
        if a.only is None or "web_first" in a.only:
            web = [web_first_request() for _ in range(a.repeats)]
    per = {"sweep": 16}
    out = {}
    for k, v in res.items():
        w, c = np.median([x[0] for x in v]), np.median([x[1] for x in v])
        n = per.get(k, 1)
        print(f"{k}: wall {w:.2f} s, CPU {c:.2f} s (median of {len(v)})" + (f"; per point {c / n:.3f} s CPU"
                                                                           if n > 1 else ""))
        out[k] = c / n
    if web:
        print(f"web_first: first POST /predict {np.median(web):.2f} s wall (median of {len(web)} starts)")
    names = {"predict": "predict_s", "ore_list": "ore_list_s", "report": "report_s", "sweep": "sweep_per_point_s",
             "optimize": "optimize_s", "score": "score_s"}
    line = " ".join(f"{names[k]}={out[k]:.3f}" for k in names if k in out)
    if web:
        line += f" web_first_s={np.median(web):.3f}"
    if floor:
        print(f"floor: importing {FLOOR_IMPORTS} costs {np.median(floor):.2f} s CPU (median of {len(floor)})")
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}")
    print(line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
