"""Write the SYNTHETIC example experiment set ``examples/experiments/`` (model-made, with noise).

There is no public measured multi-shaft-mill data. This script makes a set of
plant surveys and laboratory single-impact tests from msmill's own model, at
stated "true" parameters, with stated noise, so that ``msmill validate`` and
``msmill calibrate`` run on a fresh machine and the tests have data with a
known answer. Nothing here is measured; every file says SYNTHETIC.

    python scripts/make_example_experiments.py [--out examples/experiments] [--seed 17]

"True" values used (chosen to differ from the msmill defaults so calibration
has something to find):

* Surveys: the default stage parameters (``"default"``: the shipped surrogate's
  posterior mean, what ``msmill calibrate`` uses unless told otherwise; they were
  made with the single-point table until issue 41, so calibrating them with the
  default gave a biased ``L_ref``).
* UG2 surveys: the model's default sub-models (``jk_t10`` breakage, ``dem_matrix_fill``
  transport), ``L_ref = 20 mm`` (default 29 mm), Tavares damage; UG2 lab tests:
  ``ab_t10`` breakage at ``L_ref = 20 mm``.
* Platreef surveys: default sub-models, ``L_ref = 40 mm``; Platreef lab tests:
  ``vogel_swebrec`` breakage with ``A = 59 %``, ``k = 0.5358 t/kWh``,
  ``E_min = 0.03 kWh/t`` at the default ``L_ref = 29 mm``, ``beta = 2.2``.
* Synthetic "measured" power of the UG2 surveys: predicted impact power plus a
  synthetic no-load term of 12 kW, plus N(0, 1 kW) noise.
* Noise: multiplicative, sigma = 0.05 on every retained sieve mass.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import warnings
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from msmill import __version__
from msmill.errors import OutOfDomainWarning
from msmill.model.experiments import experiment_from_dict, write_experiment
from msmill.model.fitting import build_breakage, impact_grid, single_impact_product
from msmill.model.mill import breakage_parameters
from msmill.model.power import power_estimate
from msmill.model.synthetic import (
    EXAMPLE_FEEDS,
    EXAMPLE_POINTS,
    EXAMPLE_SIGMA,
    EXAMPLE_TRUE_L_REF_MM,
    SIEVES_MM,
    model_surveys,
    synthetic_impact_test,
)
from msmill.psd import PSD

ROOT = Path(__file__).resolve().parents[1]
NO_LOAD_KW = 12.0
#: Stage parameters of the surveys: the default provider (``msmill calibrate``'s default).
STAGE_PARAMETERS = "default"
SWEBREC_TRUE = {"A_pct": 59.0, "b_t_per_kwh": 0.5358, "e_min_kwh_t": 0.03, "swebrec_b": 2.2}  # L_ref: ore default 29 mm

LAB_FEEDS = {"13x16": {"size_mm": [13.2, 16.0], "passing_pct": [0.0, 100.0]},
             "26x32": {"size_mm": [26.5, 31.5], "passing_pct": [0.0, 100.0]}}
LAB_SPEEDS_M_S = (15.0, 25.0, 35.0, 45.0)


def surveys(rng: np.random.Generator) -> list:
    out = []
    for ore_name, points in EXAMPLE_POINTS.items():
        specs = [(f"{ore_name.lower()}-p{j + 1}-{fk}", EXAMPLE_FEEDS[fk], tph,
                  {"speed_rpm": rpm, "bottom_speed_factor": 2.0, "gate_deg": gate})
                 for j, (tph, rpm, gate, feeds) in enumerate(points) for fk in feeds]
        power = None
        if ore_name == "UG2":
            def power(e, res):
                return power_estimate(res).impact_kw + NO_LOAD_KW + rng.normal(0.0, 1.0)
        how = (f"msmill {__version__} expected-value model, default sub-models (jk_t10 breakage) with L_ref = "
               f"{EXAMPLE_TRUE_L_REF_MM[ore_name]:g} mm, tavares damage, the default stage parameters ({STAGE_PARAMETERS!r}: "
               "the shipped surrogate's posterior mean)"
               + (f"; power = predicted impact power + {NO_LOAD_KW:g} kW synthetic no-load + N(0, 1 kW)"
                  if power is not None else ""))
        out += model_surveys(ore_name, specs, {"l_ref_mm": EXAMPLE_TRUE_L_REF_MM[ore_name]}, EXAMPLE_SIGMA, rng, how=how,
                             power=power, stage_parameters=STAGE_PARAMETERS)
    return out


def impact_tests(rng: np.random.Generator) -> list:
    out = []
    for ore_name in ("UG2", "Platreef"):
        bp = breakage_parameters(ore_name)
        if ore_name == "UG2":
            brk = build_breakage("ab_t10", dataclasses.replace(bp, l_ref_mm=EXAMPLE_TRUE_L_REF_MM["UG2"]), {})
            how = "single impact, ab_t10 breakage, A = 71.8 %, b = 1.67 t/kWh, L_ref = 20 mm"
        else:
            brk = build_breakage("vogel_swebrec", bp, SWEBREC_TRUE)
            how = "single impact, vogel_swebrec breakage, " + ", ".join(f"{k} = {v:g}" for k, v in SWEBREC_TRUE.items())
        for fk, feed in LAB_FEEDS.items():
            for v in LAB_SPEEDS_M_S:
                ident = f"{ore_name.lower()}-lab-{fk}-{v:g}ms"
                draft = experiment_from_dict({"kind": "single_impact", "id": ident, "ore": ore_name,
                                              "source": "draft", "impact_speed_m_s": v, "feed": feed,
                                              "product": {"size_mm": list(SIEVES_MM),
                                                          "passing_pct": list(np.linspace(0, 100, len(SIEVES_MM)))}})
                grid = impact_grid([draft])
                frac = single_impact_product(brk, grid, draft.feed_psd.rebin(grid).fractions, v)
                out.append(synthetic_impact_test(ident, ore_name, feed, v, PSD(grid, frac, validate=False),
                                                 EXAMPLE_SIGMA, rng, f"msmill {__version__} model: {how}"))
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "examples" / "experiments")
    ap.add_argument("--seed", type=int, default=17)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutOfDomainWarning)
        exps = surveys(rng) + impact_tests(rng)
    args.out.mkdir(parents=True, exist_ok=True)
    for old in args.out.glob("*.toml"):
        old.unlink()
    for e in exps:
        write_experiment(e, args.out / f"{e.id}.toml")
    from msmill.provenance import git_commit

    commit = git_commit() or ""
    prov = {"SYNTHETIC": "model-made example data, not measurements",
            "command": "python scripts/make_example_experiments.py " + " ".join(argv or sys.argv[1:]),
            "msmill_version": __version__, "git_commit": commit,
            "date_utc": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"), "seed": args.seed,
            "noise_sigma": EXAMPLE_SIGMA, "true_l_ref_mm": EXAMPLE_TRUE_L_REF_MM, "synthetic_no_load_kw": NO_LOAD_KW,
            "platreef_lab_vogel_swebrec_true": SWEBREC_TRUE, "ug2_lab_ab_t10_true": {"A_pct": 71.8, "l_ref_mm": 20.0},
            "stage_parameters": f"{STAGE_PARAMETERS} (the shipped surrogate's posterior mean)",
            "files": sorted(f"{e.id}.toml" for e in exps)}
    tmp = args.out / "PROVENANCE.json.tmp"
    tmp.write_text(json.dumps(prov, indent=2) + "\n", encoding="utf-8")
    tmp.replace(args.out / "PROVENANCE.json")
    print(f"wrote {len(exps)} SYNTHETIC experiments to {args.out}")


if __name__ == "__main__":
    main()
