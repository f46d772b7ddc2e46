#!/usr/bin/env bash
# One short session on an NVIDIA GPU machine: does the cuda_ad_rgb path work, how fast is it
# against llvm_ad_rgb on the same machine, what would the full training set (configs/data/v2.json)
# cost on it, and does training on CUDA run and resume. Every stage is time-boxed and logs to
# $OUT (default ./gpu_out); a stage that fails is reported and the next one still runs.
#
#   OUT=/tmp/gpu_out benchmarks/gpu_session.sh            # deps importable already
#   SITE=site.tar.xz benchmarks/gpu_session.sh            # unpack carried packages first
#
# Stages (seconds, at most): probe 60, renderer tests 120, render timings 225, data generation
# 130, training 2 x 45 (the second resumes the first): under 10 minutes in all. Not in the
# default run: estimate 150 (what configs/data/v2.json would take there, measured by
# `ppmrecon-train generate --estimate`; STAGES=estimate, ESTIMATE_WORKERS=N).
set -u
GPU_VARIANT=${GPU_VARIANT:-cuda_ad_rgb}   # llvm_ad_rgb + TORCH_DEVICE=cpu: a dry run of the plumbing on a CPU
TORCH_DEVICE=${TORCH_DEVICE:-cuda}
OUT=${OUT:-$PWD/gpu_out}
mkdir -p "$OUT"
LOG=$OUT/gpu.log
REPO=$(cd "$(dirname "$0")/.." && pwd)
WORK=${WORK:-/tmp/ppmrecon_gpu}
mkdir -p "$WORK/bin"
exec > >(tee -a "$LOG") 2>&1
export PYTHONUNBUFFERED=1

if [ -n "${SITE:-}" ]; then
    mkdir -p "$WORK/site" && tar -xJf "$SITE" -C "$WORK/site" || { echo "cannot unpack $SITE"; exit 1; }
    export PYTHONPATH="$WORK/site:$REPO${PYTHONPATH:+:$PYTHONPATH}"
else
    export PYTHONPATH="$REPO${PYTHONPATH:+:$PYTHONPATH}"
fi
for cmd in render:ppmrecon.render.cli:entry train:ppmrecon.train.cli:entry compare:ppmrecon.compare:entry; do
    IFS=: read -r name mod fn <<<"$cmd"
    printf '#!/usr/bin/env python3\nimport sys\nfrom %s import %s\nif __name__ == "__main__":\n    sys.exit(%s())\n' "$mod" "$fn" "$fn" >"$WORK/bin/ppmrecon-$name"
    chmod +x "$WORK/bin/ppmrecon-$name"
done
export PATH="$WORK/bin:$PATH"
STAGES=${STAGES:-probe tests render data train}   # a subset reruns part of the session
stage() { echo; echo "=== $1 ($(date -u +%T))"; }
wants() { [[ " $STAGES " == *" $1 "* ]]; }

if wants probe; then
stage "probe"
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
nproc
GPU_VARIANT=$GPU_VARIANT timeout 60 python3 - <<'EOF'
import os, time, mitsuba as mi, drjit as dr, torch
print("mitsuba", mi.__version__, "drjit", dr.__version__, "torch", torch.__version__, "cuda", torch.cuda.is_available())
t = time.perf_counter(); mi.set_variant(os.environ["GPU_VARIANT"])
scene = mi.load_dict({"type": "scene", "s": {"type": "sphere"}})
ray = mi.Ray3f(mi.Point3f(0, 0, -5), mi.Vector3f(0, 0, 1))
si = scene.ray_intersect(ray)
print(os.environ["GPU_VARIANT"], ": hit t =", si.t, f"({time.perf_counter() - t:.1f} s to first hit)")
EOF
echo "probe rc=$?"
fi

if wants tests; then
stage "renderer tests on cuda_ad_rgb (PPMRECON_VARIANT)"
PPMRECON_VARIANT=$GPU_VARIANT timeout 120 python3 -m pytest -q -x -p no:cacheprovider \
    "$REPO/tests/test_backend.py" "$REPO/tests/test_render.py" "$REPO/tests/test_resume.py" \
    "$REPO/tests/test_appm.py" 2>&1 | tail -25
echo "tests rc=${PIPESTATUS[0]}"
fi

if wants render; then
stage "render timings: default scene, 1280x720, 64 passes, 131072 photons/pass, seed 0"
cd "$WORK"
for v in $GPU_VARIANT llvm_ad_rgb; do
    TIMEFORMAT="$v: %R s wall"
    time timeout 70 ppmrecon-render --variant $v --resolution 1280x720 --passes 64 --seed 0 -q -o "$WORK/t_$v.exr"
done
timeout 40 ppmrecon-render --variant $GPU_VARIANT --resolution 1280x720 --passes 64 --photons 1048576 --seed 0 -q \
    -o "$WORK/t_cuda_1m.exr" && echo "cuda 1M photons: ok"
timeout 45 ppmrecon-render --variant $GPU_VARIANT --single --resolution 1280x720 --passes 256 --photons 1048576 \
    --seed 7 -q -o "$WORK/ref_cuda.exr" && echo "cuda single-bandwidth reference (256 x 1M, seed 7): ok"
python3 - "$WORK" <<'EOF'
import json, sys
from pathlib import Path
import numpy as np
from ppmrecon import buffers as B, metrics as M
work = Path(sys.argv[1]); out = {}
for name in ("t_cuda_ad_rgb", "t_llvm_ad_rgb", "t_cuda_1m"):
    p = work / f"{name}.exr"
    if not p.exists():
        continue
    h = B.read_buffers(p).header
    out[name] = {k.split(".", 1)[1]: v for k, v in h.items() if "seconds" in k or k.endswith(("variant", "passes", "photons_per_pass"))}
    out[name]["nonfinite_samples"] = h.get("ppmrecon.nonfinite_samples")
ref_p = work / "ref_cuda.exr"
if ref_p.exists():
    ref, _ = B.read_rgb(ref_p)
    for name in ("t_cuda_ad_rgb", "t_llvm_ad_rgb", "t_cuda_1m"):
        p = work / f"{name}.exr"
        if p.exists():
            est = B.read_buffers(p).estimates
            out[name]["relmse_vs_cuda_reference"] = [float(M.relmse(e, ref)) for e in est]
            out[name]["luminance_ratio"] = [float(M.luminance_ratio(e, ref)) for e in est]
a, b = work / "t_cuda_ad_rgb.exr", work / "t_llvm_ad_rgb.exr"
if a.exists() and b.exists():
    ea, eb = B.read_buffers(a).estimates, B.read_buffers(b).estimates
    out["cuda_vs_llvm_same_seed_relmse"] = [float(M.relmse(x, y)) for x, y in zip(ea, eb)]
print(json.dumps(out, indent=1))
(Path(sys.argv[2] if len(sys.argv) > 2 else ".") / "render.json").write_text(json.dumps(out, indent=1))
EOF
cp -f "$WORK/render.json" "$OUT/render.json" 2>/dev/null
fi

if wants data; then
stage "data generation on $GPU_VARIANT: configs/data/v2_cpu.json's first 3 scenes (data/v3_cpu's 0000-0002)"
python3 - "$REPO" "$WORK/gpu_data.json" <<'EOF'
import json, sys
cfg = json.load(open(f"{sys.argv[1]}/ppmrecon/data/configs/data/v2_cpu.json"))
cfg.update(scenes=3, _doc="gpu_session.sh: v2_cpu.json's first 3 scenes")
json.dump(cfg, open(sys.argv[2], "w"))
EOF
PPMRECON_VARIANT=$GPU_VARIANT timeout 130 ppmrecon-train generate --config "$WORK/gpu_data.json" \
    --out "$WORK/gdata" --workers 4 -q
echo "generate rc=$?"
mkdir -p "$OUT/gdata"
cp -f "$WORK/gdata/manifest.json" "$OUT/gdata/" 2>/dev/null
for d in "$WORK"/gdata/0*/; do
    [ -f "$d/reference.exr" ] && cp -f "$d/reference.exr" "$OUT/gdata/$(basename "$d")_reference.exr"
done
python3 - "$WORK/gdata" <<'EOF'
import json, sys
from pathlib import Path
m = Path(sys.argv[1]) / "manifest.json"
if m.exists():
    print(json.dumps(json.loads(m.read_text()), indent=None)[:6000])
EOF
fi

if wants estimate; then
stage "the full training set's cost on $GPU_VARIANT (ppmrecon-train generate --config v2 --estimate)"
PPMRECON_VARIANT=$GPU_VARIANT timeout 150 ppmrecon-train generate --config v2 --estimate --workers "${ESTIMATE_WORKERS:-2}" -q
echo "estimate rc=$?"
fi

if wants train; then
stage "training on cuda: preset small, 30 s, then --resume for 30 s more"
for extra in "" "--resume"; do
    timeout 45 ppmrecon-train fit "$WORK/gdata" --out "$WORK/run" --config cpu_v2 --preset small \
        --device $TORCH_DEVICE --epochs 50 --steps-per-epoch 50 --max-seconds 30 -q $extra
    echo "train $extra rc=$?"
done
python3 - "$WORK/run/history.json" <<'EOF'
import json, sys
from pathlib import Path
p = Path(sys.argv[1])
if p.exists():
    h = json.loads(p.read_text())
    print(json.dumps(h, indent=None)[:4000])
EOF
cp -f "$WORK/run/history.json" "$OUT/train_history.json" 2>/dev/null
fi

echo; echo "=== done ($(date -u +%T))"
