"""Write (or check) the engine's reference trajectories for the bitwise re-layout test.

Two short runs: a dense, frictional, damped periodic gas (1200 spheres, solid
fraction ~0.3, 400 steps, threaded and serial kernels) and the default mill
slice at 30 mm rock (rotating geometry, sources, sinks) for 0.4 s of mill
time. Per run it stores the final particle state ordered by particle id and
the contact events ordered by (owner, partner, onset) (:mod:`msmill.dem.reference`), and writes their
SHA-256 digests with provenance, so a change of the
engine's memory layout can be checked to leave every bit unchanged
(``tests/dem/test_reference_trajectory.py``). A change that reorders sums
(e.g. a different particle sort) changes the bits; such a change must then
regenerate this file with this script and say so.

Run::

    python scripts/dem_reference_trajectory.py [--out tests/dem/data/trajectory_reference.json]
    python scripts/dem_reference_trajectory.py --check   # compare with the stored digests, run by run
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
from pathlib import Path

import numpy as np

import msmill
from msmill.dem.reference import all_runs, digest, host_cpu, host_cpu_features

OUT = Path(__file__).resolve().parents[1] / "tests" / "dem" / "data" / "trajectory_reference.json"

def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--check", action="store_true", help="compare with --out instead of writing it")
    args = ap.parse_args()
    res = all_runs()
    hashes = {k: digest(v) for k, v in res.items()}
    if args.check:
        ref = json.loads(args.out.read_text())["sha256"]
        for k, h in hashes.items():
            print(f"{k}: {'identical' if ref.get(k) == h else 'DIFFERS'}")
        print(f"identical={all(ref.get(k) == h for k, h in hashes.items())}")
        return
    from msmill.provenance import git_commit

    commit = git_commit() or ""
    prov = {"command": "python scripts/dem_reference_trajectory.py", "commit": commit,
            "msmill_version": msmill.__version__,
            "date_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "numba": __import__("numba").__version__, "numpy": np.__version__, "host_cpu": host_cpu(),
            "host_cpu_features": host_cpu_features(),
            "runs": {"gas": "1200 spheres r 5 mm, E 2e10, e 0.5, mu 0.4, 400 steps dt 1e-6 s, seed 7",
                     "mill": "default slice, 30 mm, 30 t/h, 1500 rpm, gates 40 deg, 0.4 s"},
            "events": {k: int(res[f"{k}/ev_int"].shape[0]) for k in ("gas_par", "gas_ser", "mill")},
            "sha256": hashes}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(prov, indent=1) + "\n")
    print(json.dumps(prov, indent=1))


if __name__ == "__main__":
    main()
