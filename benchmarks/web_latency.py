"""Latency of the web API for a slider move: one ``POST /predict`` at a changed operating point.

Builds the app in-process (FastAPI TestClient, no network), warms the mill
cache with the shipped UG2 example, then alternates feed-rate and speed moves
(each a new operating point) and reports the median and worst request time.
The issue's target: an updated result in under 1 s on this 2-core machine.

Run: ``python benchmarks/web_latency.py [--moves 20]``; last line
``moves=<n> cold_s=<t> median_s=<t> max_s=<t>``.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--moves", type=int, default=20)
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient

    from msmill.web.app import create_app

    client = TestClient(create_app())
    req = client.get("/defaults").json()
    t0 = time.perf_counter()
    assert client.post("/predict", json=req).status_code == 200
    cold = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    times = []
    for i in range(args.moves):
        if i % 2:
            req["feed"]["rate_tph"] = float(rng.uniform(10, 60))
        else:
            req["operating"]["speed_rpm"] = float(rng.uniform(1200, 1900))
        t = time.perf_counter()
        r = client.post("/predict", json=req)
        times.append(time.perf_counter() - t)
        assert r.status_code == 200, r.text
    print(f"cold (first request, builds the mill): {cold:.3f} s")
    print(f"slider moves: median {np.median(times):.3f} s, max {max(times):.3f} s over {len(times)}")
    print(f"moves={len(times)} cold_s={cold:.3f} median_s={np.median(times):.3f} max_s={max(times):.3f}")


if __name__ == "__main__":
    main()
