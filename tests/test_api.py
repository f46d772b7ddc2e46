"""The Python API (ppmrecon.api): docstring examples, round trips, the commands writing
what the API returns, the Mitsuba adapter and plugin, one-line errors."""

from __future__ import annotations

import doctest
import importlib
from pathlib import Path
from unittest import mock

import numpy as np
import pytest

import ppmrecon
from ppmrecon import buffers as B
from ppmrecon.errors import UsageError

# Every module whose docstrings carry the API's runnable examples.
DOC_MODULES = ("ppmrecon.api", "ppmrecon.mitsuba_plugin", "ppmrecon.data")
TINY = dict(passes=2, photons=4096, resolution=16)


def _doctests() -> list[doctest.DocTest]:
    finder = doctest.DocTestFinder()
    tests = [t for name in DOC_MODULES for t in finder.find(importlib.import_module(name)) if t.examples]
    return sorted(tests, key=lambda t: t.name)


@pytest.mark.parametrize("test", _doctests(), ids=lambda t: t.name)
def test_docstring_example(test):
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS)
    result = runner.run(test, out=lambda text: pytest.fail(text, pytrace=False))
    assert result.attempted > 0 and result.failed == 0


def test_every_public_function_has_an_example():
    names = [n for n in ppmrecon.__all__ if n not in ("BufferFile",)]
    tested = {t.name.rsplit(".", 1)[-1] for t in _doctests()}
    assert set(names) <= tested, sorted(set(names) - tested)


@pytest.fixture(scope="module")
def plane() -> B.BufferFile:
    return ppmrecon.render("plane_point", **TINY)


def test_render_round_trips_through_a_file(plane, tmp_path):
    ppmrecon.save(tmp_path / "p.exr", plane)
    again = ppmrecon.load_buffers(tmp_path / "p.exr")
    for name in ("estimates", "variances", "radii", "albedo", "normal", "depth"):
        np.testing.assert_array_equal(getattr(again, name), getattr(plane, name), err_msg=name)
    assert again.header[B.H_PASSES] == 2 and again.header[B.H_SCENE] == "plane_point"
    assert again.header["ppmrecon.variant"] in ("llvm_ad_rgb", "cuda_ad_rgb")


def test_the_render_command_writes_what_the_api_returns(plane, tmp_path):
    from ppmrecon.render.cli import main

    out = tmp_path / "cli.exr"
    assert main(["plane_point", "--passes", "2", "--photons", "4096", "--resolution", "16",
                 "--quiet", "--no-state", "-o", str(out)]) == 0
    np.testing.assert_array_equal(B.read_buffers(out).estimates, plane.estimates)


def test_the_denoise_command_writes_what_the_api_returns(plane, tmp_path):
    from ppmrecon.model.cli import main

    ppmrecon.save(tmp_path / "p.exr", plane)
    assert main([str(tmp_path / "p.exr"), "--quiet"]) == 0
    written = ppmrecon.load_image(tmp_path / "p_denoised.exr")
    np.testing.assert_allclose(ppmrecon.denoise(tmp_path / "p.exr"), written, rtol=1e-6, atol=1e-7)
    assert ppmrecon.denoise(plane).dtype == np.float32


def test_denoise_takes_a_model_object_and_a_path(plane, tmp_path):
    from ppmrecon.model import checkpoint as C

    C.init_checkpoint(tmp_path / "untrained.pt", "tiny", seed=3)
    by_path = ppmrecon.denoise(plane, tmp_path / "untrained.pt", guard="off")
    by_object = ppmrecon.denoise(plane, ppmrecon.load_model(tmp_path / "untrained.pt"), guard="off")
    np.testing.assert_array_equal(by_path, by_object)
    assert not np.array_equal(by_path, ppmrecon.denoise(plane, guard="off"))  # not the shipped model


def test_an_image_round_trips_with_its_header(tmp_path):
    rgb = np.random.default_rng(1).random((5, 7, 3)).astype(np.float32)
    ppmrecon.save(tmp_path / "i.exr", rgb, header={"ppmrecon.note": "x"})
    np.testing.assert_array_equal(ppmrecon.load_image(tmp_path / "i.exr"), rgb)
    assert B.read_rgb(tmp_path / "i.exr")[1]["ppmrecon.note"] == "x"


def test_compare_scores_like_the_command(plane, tmp_path):
    from ppmrecon.compare import main

    ref = plane.estimates[4]
    ppmrecon.save(tmp_path / "ref.exr", ref)
    ppmrecon.save(tmp_path / "p.exr", plane)
    assert main([str(tmp_path / "ref.exr"), str(tmp_path / "p.exr"), "--layers", "y",
                 "--json", str(tmp_path / "s.json")]) == 0
    import json
    expected = json.loads((tmp_path / "s.json").read_text())["scores"][0]
    for got in (ppmrecon.compare(plane, ref, layer="y"), ppmrecon.compare(tmp_path / "p.exr", tmp_path / "ref.exr", "y")):
        assert got["relmse"] == pytest.approx(expected["relmse"], rel=1e-6)
        assert got["relmse_trimmed"] == pytest.approx(expected["relmse_trimmed"], rel=1e-6)
        assert got["passes"] == 2 and got["method"] == "sppm"
    # a reference at twice the size is area-averaged down, as the command does
    big = np.repeat(np.repeat(ref, 2, axis=0), 2, axis=1)
    assert ppmrecon.compare(plane.estimates[0], big)["relmse"] == pytest.approx(
        ppmrecon.compare(plane.estimates[0], ref)["relmse"], rel=1e-6)


def _small_box(width: int = 12, height: int = 12, max_depth: int = 4) -> dict:
    import mitsuba as mi

    box = mi.cornell_box()
    box["sensor"]["film"].update(width=width, height=height)
    box["integrator"] = {"type": "path", "max_depth": max_depth}
    return box


def test_a_mitsuba_scene_and_its_dict_render_alike(plane):
    import mitsuba as mi

    box = _small_box()
    from_dict = ppmrecon.render(box, passes=2, photons=4096)
    from_scene = ppmrecon.render(mi.load_dict(box), passes=2, photons=4096)
    np.testing.assert_array_equal(from_dict.estimates, from_scene.estimates)
    assert from_dict.estimates.shape == (5, 12, 12, 3) and from_dict.estimates[1].mean() > 0
    assert from_dict.header["ppmrecon.max_depth"] == 4  # read from the scene's integrator
    assert box["sensor"]["film"]["width"] == 12  # the user's dict is not changed


def test_a_scene_dict_takes_a_resolution_and_keeps_its_aspect():
    from ppmrecon.scene.loader import load_mitsuba

    box = _small_box(40, 20)
    assert (load_mitsuba(box, resolution=10).width, load_mitsuba(box, resolution=10).height) == (10, 5)
    loaded = load_mitsuba(box, resolution=(6, 9))
    assert (loaded.width, loaded.height, loaded.max_depth) == (6, 9, 4)
    assert box["sensor"]["film"]["width"] == 40


@pytest.mark.parametrize("scene,kwargs,message", [
    ({"type": "shape"}, {}, 'needs "type": "scene"'),
    ("no/such/scene.xml", {}, "no such scene file"),
    ("plane_point", {"method": "nope"}, "unknown method 'nope'"),
    ("plane_point", {"passes": None}, "give passes or time_budget"),
    ("plane_point", {"method_params": {"beta": 2.0}}, "takes no option beta"),
])
def test_render_errors_are_one_line(scene, kwargs, message):
    with pytest.raises(UsageError, match=message) as err:
        ppmrecon.render(scene, **{**TINY, **kwargs})
    assert "\n" not in str(err.value)


def test_unsupported_mitsuba_content_is_refused():
    import mitsuba as mi

    box = _small_box()
    with pytest.raises(UsageError, match="resolution= applies to scene files and dicts"):
        ppmrecon.render(mi.load_dict(box), passes=1, resolution=8)
    box["light"]["emitter"] = {"type": "directionalarea", "radiance": 1.0}
    with pytest.raises(UsageError, match="emitter DirectionalArea is not supported"):
        ppmrecon.render(box, passes=1)
    del box["light"]
    with pytest.raises(UsageError, match="the scene has no emitter"):
        ppmrecon.render(box, passes=1)


def test_save_and_compare_errors(plane, tmp_path):
    with pytest.raises(UsageError, match=r"x\.png: ppmrecon writes OpenEXR"):
        ppmrecon.save(tmp_path / "x.png", plane)
    with pytest.raises(UsageError, match=r"expected an \(H, W, 3\) image, got shape \(4, 4\)"):
        ppmrecon.save(tmp_path / "x.exr", np.zeros((4, 4)))
    with pytest.raises(UsageError, match="aspect ratios differ"):
        ppmrecon.compare(plane.estimates[0], np.ones((16, 8, 3), np.float32))
    with pytest.raises(UsageError, match="layer 'w'"):
        ppmrecon.compare(plane, plane.estimates[0], layer="w")
    with pytest.raises(UsageError, match="guard must be on, off or model"):
        ppmrecon.denoise(plane, guard="maybe")


def test_render_reports_progress():
    seen = []
    ppmrecon.render("plane_point", passes=3, photons=1024, resolution=8, progress=lambda n, s: seen.append(n))
    assert seen == [1, 2, 3]


def test_render_and_compare_stay_importable_modules():
    # ppmrecon.render is the renderer's subpackage and the API function at once.
    import ppmrecon.render.cli as cli

    assert cli.PROG == "ppmrecon-render" and callable(ppmrecon.render) and callable(ppmrecon.compare)
    with mock.patch("ppmrecon.render.cli.PROG", "patched"):
        assert ppmrecon.render.cli.PROG == "patched"
    assert ppmrecon.compare.PROG == "ppmrecon-compare"
    import inspect
    assert "passes" in inspect.signature(ppmrecon.render).parameters


def test_package_data_is_found_through_the_package():
    from ppmrecon.data import CONFIGS, MODELS, SCENES

    package = Path(ppmrecon.__file__).parent / "data"
    assert SCENES == package / "scenes" and MODELS == package / "models" and CONFIGS == package / "configs"
    assert set(ppmrecon.builtin_scenes()) >= {"cornell_caustics", "water_caustic", "plane_point"}
    assert (SCENES / "water_surface.ply").is_file() and (MODELS / "default.pt").is_file()
