"""Benchmark: how much of the surrogate's stream error is the training runs' own sampling noise.

Loads a surrogate file (default: the shipped default surrogate) and, for every
transport-stream target (``sN.streams.0`` = ln(kickback / pass-through),
``sN.streams.1`` = ln(refeed / pass-through) of stage N), compares the closed-form leave-one-out error of
the GP (:meth:`msmill.surrogate.gp.SurrogateGP.loo`, target units) with the
sampling error the training runs themselves carry (their stored sampling
variances, the same units). Their difference is the part of the LOO error
that interpolation adds:

    interpolation^2 = max(LOO mse - mean sampling variance, 0)

The adaptive window stops when every stream's sampling error is at
``RunSettings.target_streams_se`` (0.02); loosening it by a factor ``f``
scales the sampling variance by ``f^2``. The last columns show what the LOO
rms would become at 0.03 (f = 1.5) if the interpolation part stayed the same,
i.e. whether the target is a cost lever or the floor of the surrogate's
stream accuracy.

Run::

    python benchmarks/stream_noise.py [--surrogate PATH]

The last line is ``targets=<n> loo_rms_median=<x> sampling_rms_median=<y> interpolation_rms_median=<z>
sampling_share_median=<sampling var / LOO mse> loo_rms_at_003_median=<x'>``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from msmill.model.providers import default_surrogate_path
from msmill.surrogate import persist


def stream_noise(path: Path, looser: float = 1.5) -> list[dict]:
    """Per stream target: LOO rms, sampling rms, interpolation rms and the LOO rms with looser targets."""
    model = persist.load(path)
    gp = model.gp_
    names = model.training_.layout.names
    mean, _var = gp.loo()
    rows = []
    for j, name in enumerate(names):
        if ".streams." not in name:
            continue
        resid = mean[:, j] - gp.Y_train_[:, j]
        mse = float(np.mean(resid**2))
        samp = float(np.mean(gp.noise_var_[:, j]))
        interp2 = max(mse - samp, 0.0)
        rows.append({"target": name, "loo_rms": mse**0.5, "sampling_rms": samp**0.5,
                     "interpolation_rms": interp2**0.5, "sampling_share": samp / mse if mse > 0 else np.nan,
                     "white_rms": float(np.sqrt(gp.white_[j]) * gp.y_std_[j]),
                     "loo_rms_looser": (interp2 + looser**2 * samp) ** 0.5})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--surrogate", type=Path, default=None, help="surrogate file (default: the shipped one)")
    args = ap.parse_args()
    path = args.surrogate or default_surrogate_path()
    if path is None or not path.is_file():
        raise SystemExit(f"--surrogate: {path or 'the shipped default'} is not a file (want a surrogate .json)")
    rows = stream_noise(path)
    if not rows:
        raise SystemExit(f"--surrogate: {path} has no stream targets")
    print(f"{path}: {len(rows)} stream targets (log-ratio units)")
    print(f"{'target':<16} {'LOO rms':>8} {'sampling':>9} {'interp.':>8} {'share':>6} {'GP white':>9} "
          f"{'LOO @0.03':>10}")
    for r in rows:
        print(f"{r['target']:<16} {r['loo_rms']:8.4f} {r['sampling_rms']:9.4f} {r['interpolation_rms']:8.4f} "
              f"{r['sampling_share']:6.2f} {r['white_rms']:9.4f} {r['loo_rms_looser']:10.4f}")
    med = {k: float(np.median([r[k] for r in rows]))
           for k in ("loo_rms", "sampling_rms", "interpolation_rms", "sampling_share", "loo_rms_looser")}
    print(f"targets={len(rows)} loo_rms_median={med['loo_rms']:.4f} sampling_rms_median={med['sampling_rms']:.4f} "
          f"interpolation_rms_median={med['interpolation_rms']:.4f} sampling_share_median={med['sampling_share']:.2f} "
          f"loo_rms_at_003_median={med['loo_rms_looser']:.4f}")


if __name__ == "__main__":
    main()
