"""Shared fixtures. Tests never read ../shared: they use the project's own scenes and data."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from ppmrecon import buffers as B


def make_buffer(h: int = 6, w: int = 7, seed: int = 0) -> B.BufferFile:
    """A small, valid, random buffer file (all layers, full header)."""
    rng = np.random.default_rng(seed)
    header = {
        B.H_VERSION: B.SCHEMA_VERSION, B.H_METHOD: "sppm", B.H_KERNEL: "constant",
        B.H_PASSES: 16, B.H_PHOTONS: 1024, B.H_ALPHA: 2.0 / 3.0, B.H_KNN: 20,
        B.H_SEED: 3, B.H_SCENE: "test", B.H_SECONDS: 1.25, "ppmrecon.stopped": "complete",
    }
    return B.BufferFile(
        estimates=rng.random((5, h, w, 3), dtype=np.float32) * 4,
        variances=rng.random((5, h, w), dtype=np.float32) * 1e-2,
        radii=rng.random((5, h, w), dtype=np.float32) * 0.1,
        albedo=rng.random((h, w, 3), dtype=np.float32),
        normal=rng.standard_normal((h, w, 3)).astype(np.float32),
        depth=rng.random((h, w), dtype=np.float32) * 5,
        header=header,
    )


@pytest.fixture
def buffer_file() -> B.BufferFile:
    return make_buffer()


@pytest.fixture(autouse=True)
def one_thread():
    """Small tensors on 2 shared cores run several times faster on one thread (and torch
    with 2 threads collapses when another job shares the cores)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


ROOT = Path(__file__).resolve().parents[1]


def load_script(folder: str, name: str):
    """The module of ``ROOT/folder/name.py`` (a benchmark or script, not a package module),
    with its folder on ``sys.path`` for its own sibling imports."""
    sys.path.insert(0, str(ROOT / folder))
    spec = importlib.util.spec_from_file_location(name, ROOT / folder / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
