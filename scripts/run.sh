#!/usr/bin/env bash
# Set up (idempotent) and run the main job on the built-in default scene:
#   render -> out/default.exr (buffer file), denoise -> out/default_denoised.exr (when a
#   model is available), and a side-by-side PNG out/default_side_by_side.png.
# Extra arguments go to ppmrecon-render (e.g. --passes 64 --resolution 512x512).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
./scripts/setup.sh
venv="${PPMRECON_VENV:-$root/.venv}"
out="${PPMRECON_OUT:-$root/out}"
mkdir -p "$out"
"$venv/bin/ppmrecon-render" --passes 32 --resolution 256x256 "$@" --output "$out/default.exr"
images=("$out/default.exr")
if "$venv/bin/python" -c "import sys, ppmrecon.model.checkpoint as c; sys.exit(0 if c.DEFAULT_MODEL.is_file() else 1)"; then
  "$venv/bin/ppmrecon-denoise" "$out/default.exr" --output "$out/default_denoised.exr"
  images+=("$out/default_denoised.exr")
fi
"$venv/bin/python" -m ppmrecon.preview "$out/default_side_by_side.png" "${images[@]}"
echo "wrote: ${images[*]} $out/default_side_by_side.png"
