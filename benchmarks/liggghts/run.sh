#!/usr/bin/env bash
# Runs the granular-gas throughput case in LIGGGHTS 3.8 with two MPI ranks, for
# comparison with benchmarks/dem_throughput.py. Needs: apt-get install liggghts
# Prints `phi=<phi> particle_steps_per_s=<number>` for phi 0.05 and 0.30.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
tmp="$(mktemp -d)"
for phi in 0.05 0.30; do
    mpirun --allow-run-as-root -np 2 liggghts -in "$here/gas.in" -var phi "$phi" \
        -log "$tmp/log.$phi" -screen none
    loop=$(grep "for 2000 steps" "$tmp/log.$phi" | awk '{print $4}')
    python3 -c "print(f'phi=$phi particle_steps_per_s={20000*2000/$loop:.4g}')"
done
rm -rf "$tmp"
