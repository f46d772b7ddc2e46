#!/usr/bin/env bash
# One command for the whole speed/accuracy study (docs/RESULTS.md):
#
#   benchmarks/study.sh SCENES_DIR [--quick]
#
# 1. set-up, with the benchmark extras (matplotlib, pyoidn);
# 2. full mode only: the generated training set data/cpu (ppmrecon/data/configs/data/cpu.json; resumable)
#    and one checkpoint per larger preset, trained on it for a fixed wall-clock budget on one
#    thread each, side by side (runs/study_small, runs/study_paper; kept when present);
# 3. benchmarks/study.py: references (cached in docs/cache), equal-time comparisons,
#    consistency curves, overheads and the preset trade -> docs/RESULTS.md + docs/figures.
# --quick skips step 2 (the preset trade then has the shipped model only) and finishes in
# under 15 minutes on 2 cores.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
scenes="${1:-}"
if [ -z "$scenes" ] || [ ! -d "$scenes" ]; then
  echo "study.sh: SCENES_DIR '${scenes}' is not a folder (usage: benchmarks/study.sh SCENES_DIR [--quick])" >&2
  exit 2
fi
shift
quick=0
for a in "$@"; do
  case "$a" in
    --quick) quick=1 ;;
    *) echo "study.sh: unknown option '$a' (only --quick)" >&2; exit 2 ;;
  esac
done
cd "$root"
./scripts/setup.sh
venv="${PPMRECON_VENV:-$root/.venv}"
"$venv/bin/python" -c "import matplotlib, pyoidn" 2>/dev/null \
  || "$venv/bin/python" -m pip --disable-pip-version-check -q install -e "$root[bench]"

if [ "$quick" = 1 ]; then
  exec "$venv/bin/python" benchmarks/study.py --scenes "$scenes" --quick
fi

# Training budgets (seconds): the same data, one thread each, run side by side.
SMALL_SECONDS="${SMALL_SECONDS:-1200}"
PAPER_SECONDS="${PAPER_SECONDS:-1200}"
mkdir -p runs
"$venv/bin/ppmrecon-train" generate --config cpu --out data/cpu --workers 2
pids=()
for preset in small paper; do
  run="runs/study_$preset"
  [ -f "$run/best.pt" ] && continue
  budget=SMALL_SECONDS; [ "$preset" = paper ] && budget=PAPER_SECONDS
  "$venv/bin/ppmrecon-train" fit data/cpu --out "$run" --config "cpu_$preset" \
    --threads 1 --max-seconds "${!budget}" > "runs/study_$preset.log" 2>&1 &
  pids+=($!)
done
for p in "${pids[@]}"; do wait "$p"; done
exec "$venv/bin/python" benchmarks/study.py --scenes "$scenes" \
  --preset-model "tiny=ppmrecon/data/models/default.pt" \
  --preset-model "small=runs/study_small/best.pt" \
  --preset-model "paper=runs/study_paper/best.pt"
