#!/usr/bin/env bash
# Build the wheel, install it in a clean virtual environment outside the checkout, and
# run the main job (render -> denoise -> preview), the other commands' --help and the
# Python API from an empty folder. Proves the package works without the repository:
# scenes, presets, configs and the shipped model must travel as package data.
#
#   scripts/check_wheel.sh [PYTHON]     (default: .venv/bin/python; tests/test_wheel.py runs it)
#
# Nothing is downloaded: the wheel is built with --no-build-isolation from PYTHON's
# setuptools, installed with --no-deps --no-index, and the heavy dependencies (torch,
# Mitsuba, ...) are reached through a .pth file naming PYTHON's site-packages, which
# comes after the clean environment's own site-packages, so the installed wheel, never
# the checkout, provides `ppmrecon`. Prints the wheel size and the timings.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
py="${1:-$root/.venv/bin/python}"
# The caller's PYTHONPATH (a checkout, say) must not stand in for the installed wheel,
# nor make pip believe ppmrecon is installed already.
unset PYTHONPATH
[ -x "$py" ] || { echo "check_wheel: no Python at $py (run ./scripts/setup.sh first)" >&2; exit 2; }
work="$(mktemp -d "${TMPDIR:-/tmp}/ppmrecon-wheel.XXXXXX")"
trap 'rm -rf "$work"' EXIT
t0=$EPOCHREALTIME

# Build from a copy of what the wheel is made of: a stale build/ or egg-info in the
# checkout cannot leak into it then.
mkdir -p "$work/src" "$work/dist" "$work/empty"
cp "$root/pyproject.toml" "$root/README.md" "$work/src/"
cp -r "$root/ppmrecon" "$work/src/"
find "$work/src" -name __pycache__ -prune -exec rm -rf {} +
(cd "$work/src" && "$py" -m pip --disable-pip-version-check -q wheel . --no-deps --no-build-isolation -w "$work/dist")
wheel=("$work"/dist/ppmrecon-*.whl)
echo "check_wheel: built $(basename "${wheel[0]}") ($(( $(stat -c %s "${wheel[0]}") / 1024 )) KB)"

"$py" -m venv --without-pip "$work/venv"
site_new="$("$work/venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
site_deps="$("$py" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
"$py" -m pip --disable-pip-version-check -q --python "$work/venv/bin/python" install --no-deps --no-index --force-reinstall "${wheel[0]}"
echo "$site_deps" > "$site_new/zz_ppmrecon_deps.pth"
t1=$EPOCHREALTIME

bin="$work/venv/bin"
cd "$work/empty"
# Where ppmrecon comes from: the clean environment, not the checkout.
"$bin/python" - "$site_new" <<'EOF'
import sys, ppmrecon
where = ppmrecon.__file__
assert where.startswith(sys.argv[1]), f"ppmrecon imported from {where}, not the installed wheel"
EOF
"$bin/ppmrecon-render" --list-scenes > scenes.txt
grep -q "^cornell_caustics (default)" scenes.txt || { echo "check_wheel: no built-in scenes" >&2; exit 1; }
"$bin/ppmrecon-render" --passes 2 --photons 4096 --resolution 24x24 --quiet -o default.exr
"$bin/ppmrecon-render" water_caustic --passes 1 --photons 2048 --resolution 16x16 --quiet -o water.exr  # a mesh (.ply) beside its XML
"$bin/ppmrecon-denoise" default.exr --quiet
"$bin/python" -m ppmrecon.preview side.png default.exr default_denoised.exr
"$bin/ppmrecon-compare" default_denoised.exr default.exr --layers z4 > compare.txt  # scores ~z^4 against the denoised image
"$bin/ppmrecon-train" --help > /dev/null
"$bin/ppmrecon-train" generate --help | grep -q "v2_cpu"
"$bin/ppmrecon-compare" --help > /dev/null
"$bin/ppmrecon-denoise" --init-checkpoint small.pt --preset small --quiet
"$bin/python" - <<'EOF'
import ppmrecon
buf = ppmrecon.render("plane_point", passes=1, photons=1024, resolution=8)
rgb = ppmrecon.denoise(buf)
assert rgb.shape == (8, 8, 3)
EOF
for f in default.exr water.exr default_denoised.exr side.png small.pt; do
  [ -s "$f" ] || { echo "check_wheel: $f was not written" >&2; exit 1; }
done
t2=$EPOCHREALTIME
"$bin/python" -c "import sys; a, b, c = map(float, sys.argv[1:]); print(f'check_wheel: ok: build+install {b - a:.1f} s, main job and commands from an empty folder {c - b:.1f} s')" "$t0" "$t1" "$t2"
