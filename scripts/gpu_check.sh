#!/usr/bin/env bash
# Issue 17's GPU checks in one command, on a machine with an NVIDIA GPU and its driver:
# the 1280x720 five-chain pass with 0.1M photons (target <= 20 ms, written to
# benchmarks/results/render_cuda_ad_rgb_1280x720_100000.{json,md}) and the whole test
# suite on Mitsuba's cuda_ad_rgb variant. Stops with one line where the variant cannot run.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
./scripts/setup.sh
venv="${PPMRECON_VENV:-$root/.venv}"
"$venv/bin/python" benchmarks/bench_render.py --variant cuda_ad_rgb --resolution 1280x720 --photons 100000 \
    --timings-only "$@"
PPMRECON_VARIANT=cuda_ad_rgb exec "$venv/bin/python" -m pytest -q
