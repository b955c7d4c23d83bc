#!/usr/bin/env bash
# Granular gas, msmill (2 threads) against LIGGGHTS 3.8 (2 MPI ranks), alternated: N rounds
# (default 8), the order swapped every round. One line per program and round:
#   round <i> <msmill|liggghts> <UTC time> load <1-min load average> ... phi=0.05 particle_steps_per_s=<x> phi=0.30 ...
# Summarise with: python benchmarks/liggghts/ratios.py FILE
# Needs: apt-get install liggghts. Run on an otherwise idle machine (pause background DEM jobs).
set -euo pipefail
root="$(cd "$(dirname "$0")/../.." && pwd)"
cd "$root"
n=${1:-8}
for i in $(seq 1 "$n"); do
  if (( i % 2 )); then order="m l"; else order="l m"; fi
  for w in $order; do
    t=$(date -u +%H:%M:%S); la=$(cut -d' ' -f1 /proc/loadavg)
    if [ "$w" = m ]; then
      out=$(python benchmarks/dem_throughput.py --threads 2 2>/dev/null | grep -E '^phi=' | tr '\n' ' ')
      echo "round $i msmill $t load $la $out"
    else
      out=$(bash benchmarks/liggghts/run.sh 2>/dev/null | tr '\n' ' ')
      echo "round $i liggghts $t load $la $out"
    fi
  done
done
