#!/usr/bin/env bash
# Idempotent set-up for ppmrecon on Debian 12 / Python 3.11 (root, no GPU needed).
#  1. Debian's libllvm19 when no libLLVM >= 16 is present (Mitsuba 3.9.1's LLVM
#     backend crashes at JIT time with the preinstalled LLVM 14/15).
#  2. A virtual environment in .venv (override with PPMRECON_VENV).
#  3. torch==2.13.0 first: the CPU build on this machine's disk, never a multi-GB CUDA wheel.
#  4. The package itself, editable, with its dev and distributed (Ray) extras: the test
#     suite runs Ray data generation on a local cluster.
# A second run only checks and returns in seconds.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="${PPMRECON_VENV:-$root/.venv}"
py="${PYTHON:-python3}"
TORCH_PIN="torch==2.13.0"

have_llvm16() {
  local f v
  for f in /usr/lib/x86_64-linux-gnu/libLLVM-*.so* /usr/lib/aarch64-linux-gnu/libLLVM-*.so* \
           /usr/lib/llvm-*/lib/libLLVM*.so*; do
    [ -e "$f" ] || continue
    v="$(basename "$f" | sed -E 's/^libLLVM-?([0-9]+).*/\1/')"
    [[ "$v" =~ ^[0-9]+$ ]] && [ "$v" -ge 16 ] && return 0
  done
  return 1
}

if ! have_llvm16; then
  echo "setup: installing Debian's libllvm19 (Mitsuba's CPU backend needs libLLVM >= 16)" >&2
  if [ "$(id -u)" -ne 0 ]; then
    echo "setup: need root to apt-get install libllvm19; run: sudo apt-get install -y libllvm19" >&2
    exit 1
  fi
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >/dev/null
fi

if [ ! -x "$venv/bin/python" ]; then
  echo "setup: creating virtual environment $venv" >&2
  "$py" -m venv "$venv"
fi
pip() { "$venv/bin/python" -m pip --disable-pip-version-check -q "$@"; }

stamp="$venv/.ppmrecon-setup-stamp"
want="$(sha256sum "$root/pyproject.toml" | cut -c1-16) $TORCH_PIN"
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] \
   && "$venv/bin/python" -c "import ppmrecon, torch" 2>/dev/null; then
  exit 0
fi

if ! "$venv/bin/python" -c "import torch, sys; sys.exit(torch.__version__.split('+')[0] != '2.13.0')" 2>/dev/null; then
  echo "setup: installing $TORCH_PIN (CPU build)" >&2
  pip install "$TORCH_PIN"
fi
echo "setup: installing ppmrecon (editable, dev and distributed extras)" >&2
pip install -e "$root[dev,distributed]"
echo "$want" > "$stamp"
