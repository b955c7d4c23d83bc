"""Speed of ``msmill ore calibrate`` on a large drop-weight CSV (issue 16: 1e6 rows in < 10 s).

Run::

    python benchmarks/calibrate_large_csv.py [n_rows]

Writes a SYNTHETIC drop-weight table (Eq. 11-12 with A = 50 %, b L / L_ref
factor 0.8/25, Gaussian noise sigma 2 % t10, seed 0; benchmark use only, in a
temporary folder, never shipped) and times the whole command in a child
process, residual table included (it prints the 30 largest residuals). The
last line is ``rows=<n> calibrate_seconds=<median of 3 runs>``.
"""

from __future__ import annotations

import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd


def synthetic_csv(path: Path, n: int) -> None:
    """A SYNTHETIC drop-weight table of ``n`` rows."""
    rng = np.random.default_rng(0)
    size = rng.uniform(5.0, 50.0, n)
    ecs = rng.uniform(0.05, 3.0, n)
    t10 = np.clip(50.0 * (1.0 - np.exp(-0.8 * ecs * size / 25.0)) + rng.normal(0.0, 2.0, n), 0.0, 100.0)
    pd.DataFrame({"size_mm": size, "ecs_kwh_t": ecs, "t10_pct": t10}).to_csv(path, index=False)


def main() -> None:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 1_000_000
    with tempfile.TemporaryDirectory() as tmp:
        csv = Path(tmp) / "dropweight_SYNTHETIC.csv"
        synthetic_csv(csv, n)
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            out = subprocess.run([sys.executable, "-m", "msmill", "ore", "calibrate", str(csv)],
                                 capture_output=True, text=True, check=True)
            times.append(time.perf_counter() - t0)
        lines = out.stdout.splitlines()
        print(next(ln for ln in lines if ln.startswith("R^2")))
        print(f"printed lines: {len(lines)}; runs (s): {', '.join(f'{t:.2f}' for t in times)}")
    print(f"rows={n} calibrate_seconds={statistics.median(times):.2f}")


if __name__ == "__main__":
    main()
