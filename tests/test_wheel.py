"""The installed package works without the repository (issue 15): scripts/check_wheel.sh
builds the wheel, installs it in a clean virtual environment outside the checkout and
runs the main job, the commands and the API from an empty folder (~30 s). Marked slow,
but part of the default suite, so CI runs it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_the_wheel_works_outside_the_checkout():
    proc = subprocess.run(["bash", str(ROOT / "scripts" / "check_wheel.sh"), sys.executable],
                          capture_output=True, text=True, timeout=540)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "check_wheel: ok" in proc.stdout
