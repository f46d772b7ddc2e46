#!/usr/bin/env bash
# Set up (idempotent) and run the test suite. README's test command; .ci/run calls it.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
./scripts/setup.sh
venv="${PPMRECON_VENV:-$root/.venv}"
# pytest exits 5 when it collects nothing, so an empty run fails here too.
exec "$venv/bin/python" -m pytest -q "$@"
