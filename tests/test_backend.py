"""The backend chooser picks llvm_ad_rgb on a machine without a GPU and it renders."""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest

from ppmrecon import backend


def test_find_libllvm_is_new_enough():
    path = backend.find_libllvm()
    assert path is not None, backend.INSTALL_HINT
    assert backend._llvm_major(path) >= backend.MIN_LLVM


@pytest.mark.parametrize("name, major", [
    ("/usr/lib/x86_64-linux-gnu/libLLVM-19.so", 19),
    ("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1", 19),
    ("/usr/lib/x86_64-linux-gnu/libLLVM-14.0.6.so.1", 14),
    ("/usr/lib/llvm-17/lib/libLLVM.so", 17),
])
def test_llvm_major_parsing(name, major):
    assert backend._llvm_major(name) == major


def test_unknown_forced_variant_is_one_line():
    with pytest.raises(backend.BackendError) as info:
        backend.choose_variant("scalar_rgb")
    assert "scalar_rgb" in str(info.value) and "\n" not in str(info.value)


@pytest.mark.skipif(shutil.which("nvidia-smi") is not None, reason="machine has a GPU")
def test_chooses_llvm_and_renders_cornell_box():
    variant = backend.choose_variant()
    assert variant == "llvm_ad_rgb"
    assert backend.find_libllvm() and os.environ.get("DRJIT_LIBLLVM_PATH")
    import mitsuba as mi

    scene_dict = mi.cornell_box()
    scene_dict["sensor"]["film"]["width"] = 16
    scene_dict["sensor"]["film"]["height"] = 16
    scene_dict["integrator"] = {"type": "path", "max_depth": 6}
    img = np.asarray(mi.render(mi.load_dict(scene_dict), spp=8))
    assert img.shape == (16, 16, 3)
    assert np.isfinite(img).all() and img.mean() > 0.05
