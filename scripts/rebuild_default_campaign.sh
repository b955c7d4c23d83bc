#!/usr/bin/env bash
# Rebuild the shipped campaign export, default surrogate, accuracy figures and results page from saved
# DEM run folders (the raw events stay outside git). This is how the 2026-12-01 artefacts were made:
#
#   RUNS=/work/demruns RESTAT=0 bash scripts/rebuild_default_campaign.sh   (RESTAT=0: the folders' statistics
#   were already recomputed by this code: msmill dem stats per folder; the campaign runner's own)
#
# RUNS holds: batch0/pt_* (scripts/design_batch.py, Sobol batch), stage_table_v3/size_*mm (the stage
# table's runs), full/size_*mm (full-mill runs paired with slice runs), campaign_raw/run* (folders the
# campaign runner saved with --raw-dir), capacity/pt_*, capacity2/pt_* (scripts/design_batch.py batches at high feed
# and narrow gates, issue 20), capacity3/pt_*, choke*/pt_* (feeds of 60-600 t/h, outside the design space: they
# feed the operating envelope, not the surrogate, msmill.pipeline.export.split_runs),
# fine*/pt_* (scripts/design_batch.py --adaptive, rock below 6 mm), rerun*/ (scripts/rerun_undersampled.py: under-sampled runs measured for longer, in place of the originals). Every folder's statistics are recomputed with this checkout's
# code first (`msmill dem stats`), so outcomes follow today's steady-state criterion; not-steady and
# choked runs are stored with their outcome (the surrogate trains on steady slice runs only).
set -euo pipefail
cd "$(dirname "$0")/.."
export RUNS="${RUNS:?set RUNS to the folder of saved run folders}"
STORE="${STORE:-$RUNS/final.sqlite}"
export MSMILL_DB="sqlite:///$STORE"
rm -f "$STORE"
folders=("$RUNS"/batch0/pt_* "$RUNS"/stage_table_v3/size_*mm "$RUNS"/full/size_*mm "$RUNS"/campaign_raw/run*
         "$RUNS"/capacity/pt_* "$RUNS"/capacity2/pt_* "$RUNS"/capacity3/pt_* "$RUNS"/choke*/pt_*
         "$RUNS"/fine*/pt_*)
# re-runs of under-sampled runs (scripts/rerun_undersampled.py, RUNS/rerun*/<hash>/) take the place of the
# runs they re-measure: one run per mode and design point. Folders without statistics are left out.
mapfile -t folders < <(python - "${folders[@]}" <<'PY'
import glob, json, os, sys
from pathlib import Path

def key(folder):
    if not (Path(folder) / "statistics.json").exists():
        return None
    st = json.loads((Path(folder) / "statistics.json").read_text(encoding="utf-8"))
    d = st["design"]
    return st["mode"], *(round(float(d[k]), 6) for k in ("size_mm", "feed_tph", "speed_rpm", "gate_deg"))

reruns = {k: f for f in sorted(glob.glob(os.environ["RUNS"] + "/rerun*/*/")) if (k := key(f)) is not None}
keys = {f: key(f) for f in sys.argv[1:]}
done = [f for f, k in keys.items() if k is not None]  # a run still going (or a pattern matching nothing) waits
kept = [f for f in done if keys[f] not in reruns]
print("\n".join(kept + sorted(f.rstrip("/") for f in reruns.values())))
print(f"{len(reruns)} re-runs replace {len(done) - len(kept)} runs; {len(sys.argv) - 1 - len(done)} folders "
      "without statistics skipped", file=sys.stderr)
PY
)
if [ "${RESTAT:-1}" = 1 ]; then
    for d in "${folders[@]}"; do python -m msmill dem stats "$d" >/dev/null; done
fi
python -m msmill db ingest --allow-not-steady "${folders[@]}"
python -m msmill campaign create default --size-range-mm 6 30 --set adaptive=true
rm -f src/msmill/data/campaigns/default/run-*.json
python scripts/campaign_export.py --out src/msmill/data/campaigns/default
python scripts/build_default_surrogate.py --loo closed --restarts 1
# the envelope: the censored capacity model when some run choked, else the lower bounds the steady runs demonstrate
python scripts/build_envelope.py || { echo "no envelope built: removing the shipped one"; rm -f src/msmill/data/envelopes/default.json; }
python benchmarks/surrogate_accuracy.py --loo closed
python scripts/campaign_results.py
