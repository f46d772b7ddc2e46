#!/usr/bin/env bash
# "How many passes do I need for relMSE X on my scene?" -- the README recipe end to end:
#   1. a reference: the --single baseline with 8x the passes of the largest snapshot and
#      another seed (plain R,G,B; compare area-averages it if it is an integer multiple
#      of the snapshots' size);
#   2. one render that leaves a buffer file at every doubling of the pass count;
#   3. every snapshot denoised in one call (the model loads once);
#   4. ppmrecon-compare: table, JSON, log-log plot with fitted slopes, crop sheet, and the
#      passes each series needs for relMSE $TARGET.
# The README figure docs/figures/passes_recipe.png is this script's plot with the
# defaults below (about 20 min on 2 CPU cores). Settings come from the environment:
#   SCENE (cornell_caustics) RES (128x128) PHOTONS (32768) LAST (128) TARGET (0.01)
#   OUT (out/passes_recipe) PY (.venv/bin/python; PPMRECON_VENV/bin/python if set)
#   FIGURE (docs/figures/passes_recipe.png; empty = do not copy)
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
scene="${SCENE:-cornell_caustics}"
res="${RES:-128x128}"
photons="${PHOTONS:-32768}"
last="${LAST:-128}"
target="${TARGET:-0.01}"
out="${OUT:-$root/out/passes_recipe}"
py="${PY:-${PPMRECON_VENV:-$root/.venv}/bin/python}"
figure="${FIGURE-docs/figures/passes_recipe.png}"
mkdir -p "$out"

# 1. reference (resumable: rerunning the script continues it instead of starting over)
ref="$out/reference.exr"
ref_passes=$((8 * last))
if [[ -f "$ref.state.npz" ]]; then
  have=$("$py" -c "import sys; from ppmrecon.render.state import read_state; print(read_state(sys.argv[1]).passes)" "$ref.state.npz")
  if (( have < ref_passes )); then
    "$py" -m ppmrecon.render.cli --resume "$ref" --passes $((ref_passes - have)) --checkpoint-every 64
  fi
else
  "$py" -m ppmrecon.render.cli "$scene" --single --resolution "$res" --photons "$photons" --seed 1000 \
    --passes "$ref_passes" --checkpoint-every 64 -o "$ref"
fi

# 2. snapshots at 4, 8, ..., LAST passes of one render
"$py" -m ppmrecon.render.cli "$scene" --resolution "$res" --photons "$photons" --seed 1 \
  --snapshots "4..$last" -o "$out/run.exr"

# 3. denoise every snapshot, one model load
"$py" -m ppmrecon.model.cli "$out/run_p*.exr"

# 4. score inputs ~z^1 and the denoised images against the reference
"$py" -m ppmrecon.compare "$ref" "$out/run_p*.exr" --layers z1 --target "$target" \
  --plot "$out/passes.png" --json "$out/passes.json" | tee "$out/passes.txt"
if [[ -n "$figure" ]]; then
  cp "$out/passes.png" "$figure"
  cp "$out/passes_crops.png" "${figure%.png}_crops.png"
  echo "copied the plots to $figure and ${figure%.png}_crops.png"
fi
