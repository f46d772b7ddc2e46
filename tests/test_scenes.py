"""Scene loading: built-in scenes, resolution override, relative files, refusals, errors."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from ppmrecon.errors import UsageError
from ppmrecon.render.scene import (DEFAULT_SCENE, LoadedScene, SceneError, builtin_scenes,
                                   load_scene)

BUILTINS = ("cornell_caustics", "glossy_spot", "water_caustic", "diffuse_glossy", "plane_point")


def scene_file(folder: Path, body: str, name: str = "s.xml", version: str = "3.0.0",
               width: int = 16, height: int = 12) -> Path:
    """A small Mitsuba 3 scene file with a sensor and ``body``."""
    text = f"""<scene version="{version}">
  <sensor type="perspective">
    <float name="fov" value="45"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="{width}"/><integer name="height" value="{height}"/>
      <rfilter type="box"/></film>
  </sensor>
  {body}
</scene>"""
    path = folder / name
    path.write_text(text)
    return path


LIT_SPHERE = ('<shape type="sphere"><bsdf type="diffuse"/></shape>'
              '<emitter type="point"><point name="position" x="0" y="3" z="3"/>'
              '<rgb name="intensity" value="10"/></emitter>')


def render(ls: LoadedScene, spp: int = 4) -> np.ndarray:
    import mitsuba as mi
    return np.array(mi.render(ls.scene, spp=spp))


# --------------------------------------------------------------------------- built-ins

def test_builtin_scene_list():
    scenes = builtin_scenes()
    assert set(BUILTINS) <= set(scenes)
    assert DEFAULT_SCENE == "cornell_caustics" and DEFAULT_SCENE in scenes
    for path in scenes.values():
        assert path.is_file() and path.suffix == ".xml"
    assert (Path(scenes[DEFAULT_SCENE]).parent / "README.md").is_file()


@pytest.mark.parametrize("name", BUILTINS)
def test_builtin_scene_loads_and_renders(name):
    ls = load_scene(name, resolution=(16, 16))
    assert ls.name == name and ls.path == builtin_scenes()[name]
    assert (ls.width, ls.height) == (16, 16)
    assert ls.max_depth is not None and ls.max_depth >= 2
    assert ls.integrator_params == {"type": "path"}
    assert len(ls.scene.emitters()) >= 1
    img = render(ls, spp=8)
    assert img.shape == (16, 16, 3)
    assert np.isfinite(img).all() and img.min() >= 0 and img.mean() > 0


def test_default_scene_when_none():
    ls = load_scene(None, resolution=8)
    assert ls.name == DEFAULT_SCENE and (ls.width, ls.height) == (8, 8)


def test_builtin_default_resolution():
    ls = load_scene("cornell_caustics")
    assert (ls.width, ls.height) == (256, 256)


def test_plane_point_matches_its_analytic_radiance():
    """The numbers documented in plane_point.xml: I = 10 W/sr at h = 1, rho = 0.5, fov 20 from 4."""
    n, sub = 16, 8
    ls = load_scene("plane_point", resolution=n)
    img = render(ls, spp=64)[..., 0]
    half = 4 * np.tan(np.radians(10))  # the film maps linearly onto the plane it faces
    c = ((np.arange(n * sub) + 0.5) / (n * sub) * 2 - 1) * half
    x, z = np.meshgrid(c, c)
    fine = 0.5 / np.pi * 10 / (1 + x ** 2 + z ** 2) ** 1.5
    expected = fine.reshape(n, sub, n, sub).mean(axis=(1, 3))  # box filter: the pixel's mean
    np.testing.assert_allclose(img, expected, rtol=2.5e-2)  # 64 random positions per pixel
    assert img.mean() == pytest.approx(expected.mean(), rel=2e-3)


def test_diffuse_glossy_has_no_delta_bsdf():
    import mitsuba as mi
    ls = load_scene("diffuse_glossy", resolution=32)
    for shape in ls.scene.shapes():
        flags = shape.bsdf().flags()
        assert not (flags & int(mi.BSDFFlags.Delta)), shape.id()


# --------------------------------------------------------------------------- resolution

def test_resolution_explicit(tmp_path):
    path = scene_file(tmp_path, LIT_SPHERE, width=80, height=60)
    ls = load_scene(path, resolution=(20, 10))
    assert (ls.width, ls.height) == (20, 10)
    assert render(ls).shape == (10, 20, 3)


def test_resolution_width_keeps_aspect(tmp_path):
    path = scene_file(tmp_path, LIT_SPHERE, width=800, height=600)
    ls = load_scene(str(path), resolution=40)
    assert (ls.width, ls.height) == (40, 30)
    ls = load_scene(str(path))
    assert (ls.width, ls.height) == (800, 600)


def test_resolution_without_film_uses_mitsuba_default_aspect(tmp_path):
    path = tmp_path / "nofilm.xml"
    path.write_text(f'<scene version="3.0.0"><sensor type="perspective"/>{LIT_SPHERE}</scene>')
    ls = load_scene(path, resolution=64)
    assert (ls.width, ls.height) == (64, 48)  # 768 x 576


@pytest.mark.parametrize("bad", [(0, 10), (-4, 4), 0, (1, 2, 3), (10.5, 4)])
def test_bad_resolution_is_a_scene_error(bad):
    with pytest.raises(SceneError, match="resolution"):
        load_scene("plane_point", resolution=bad)


# --------------------------------------------------------------------------- files

def test_relative_files_resolve_against_the_scene_folder(tmp_path, monkeypatch):
    from ppmrecon.render.scene import ensure_variant
    ensure_variant()
    import mitsuba as mi
    sub = tmp_path / "scenes" / "a"
    sub.mkdir(parents=True)
    mesh = mi.load_dict({"type": "rectangle"})
    mesh.write_ply(str(sub / "quad.ply"))
    tex = np.full((4, 4, 3), 200, np.uint8)
    mi.Bitmap(tex).write(str(sub / "tex.png"))
    body = ('<shape type="ply"><string name="filename" value="quad.ply"/>'
            '<bsdf type="diffuse"><texture type="bitmap" name="reflectance">'
            '<string name="filename" value="tex.png"/></texture></bsdf></shape>'
            '<emitter type="constant"><rgb name="radiance" value="1"/></emitter>')
    path = scene_file(sub, body)
    elsewhere = tmp_path / "cwd"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    fr = mi.file_resolver()
    before = [str(fr[i]) for i in range(len(fr))]
    ls = load_scene(os.path.relpath(path, elsewhere))
    assert render(ls).mean() > 0
    fr = mi.file_resolver()
    assert [str(fr[i]) for i in range(len(fr))] == before  # the resolver is restored


def test_missing_referenced_file_names_it(tmp_path):
    path = scene_file(tmp_path, '<shape type="obj" id="teapot"><string name="filename" value="meshes/teapot.obj"/></shape>')
    with pytest.raises(SceneError) as err:
        load_scene(path)
    msg = str(err.value)
    assert "\n" not in msg and "meshes/teapot.obj" in msg and '<shape type="obj" id="teapot">' in msg


# --------------------------------------------------------------------------- refusals

def one_line_error(path, needle: str) -> str:
    with pytest.raises(SceneError) as err:
        load_scene(path)
    msg = str(err.value)
    assert "\n" not in msg, msg
    assert msg.startswith(str(path)), msg
    assert needle in msg, msg
    return msg


def test_refuses_a_medium(tmp_path):
    path = scene_file(tmp_path, '<medium type="homogeneous" id="fog"><float name="sigma_t" value="1"/></medium>'
                                + LIT_SPHERE)
    msg = one_line_error(path, '<medium type="homogeneous" id="fog">')
    assert "participating media" in msg


def test_refuses_a_shape_with_an_interior_medium(tmp_path):
    path = scene_file(tmp_path, '<shape type="sphere"><ref name="interior" id="smoke"/></shape>' + LIT_SPHERE)
    one_line_error(path, '<ref name="interior" id="smoke">')


def test_refuses_a_nested_medium(tmp_path):
    path = scene_file(tmp_path, '<shape type="sphere"><bsdf type="null"/><medium type="homogeneous" name="interior"/>'
                                '</shape>' + LIT_SPHERE)
    one_line_error(path, '<medium type="homogeneous" name="interior">')


@pytest.mark.parametrize("etype", ["directionalarea", "irradiancemeter"])
def test_refuses_an_unsupported_emitter_type(tmp_path, etype):
    path = scene_file(tmp_path, f'<emitter type="{etype}"/>' + LIT_SPHERE)
    msg = one_line_error(path, f"emitter type '{etype}'")
    assert f'<emitter type="{etype}">' in msg


def test_refuses_an_unsupported_sensor_type(tmp_path):
    path = tmp_path / "rm.xml"
    path.write_text(f'<scene version="3.0.0"><sensor type="radiancemeter"/>{LIT_SPHERE}</scene>')
    one_line_error(path, "sensor type 'radiancemeter'")


def test_refuses_unsupported_emitter_in_06_file_too(tmp_path):
    path = tmp_path / "sky.xml"
    path.write_text('<scene version="0.6.0">\n<emitter type="envmap_rgbe"/></scene>')
    one_line_error(path, 'sky.xml:2: Mitsuba 0.6 element <emitter type="envmap_rgbe">')


# --------------------------------------------------------------------------- errors

def test_missing_file_is_a_one_line_usage_error(tmp_path):
    path = tmp_path / "nope.xml"
    with pytest.raises(SceneError) as err:
        load_scene(path)
    msg = str(err.value)
    assert "\n" not in msg and str(path) in msg and "no such scene file" in msg
    assert isinstance(err.value, UsageError) and err.value.exit_code == 2


def test_unknown_builtin_name_lists_the_builtins():
    with pytest.raises(SceneError, match="cornell_caustics"):
        load_scene("no_such_scene")


def test_broken_xml_is_one_line(tmp_path):
    path = tmp_path / "broken.xml"
    path.write_text('<scene version="3.0.0"><shape type="sphere">\n<bsdf type="diffuse">\n</scene>')
    msg = one_line_error(path, "not valid XML")
    assert "line 3" in msg


def test_not_a_scene_root(tmp_path):
    path = tmp_path / "x.xml"
    path.write_text('<bsdf type="diffuse"/>')
    one_line_error(path, "root element is <bsdf>")


def test_missing_version(tmp_path):
    path = tmp_path / "x.xml"
    path.write_text("<scene/>")
    one_line_error(path, "no version attribute")


def test_mitsuba_load_error_is_stripped_to_one_line(tmp_path):
    path = scene_file(tmp_path, '<bsdf type="roughconductor" id="m"><string name="distribution" value="as"/></bsdf>'
                                '<shape type="sphere"><ref id="m"/><float name="wobbliness" value="1"/></shape>')
    msg = one_line_error(path, 'invalid distribution "as"')
    assert ".cpp:" not in msg and "line 1, col" not in msg


def test_file_integrator_is_replaced_by_path_keeping_max_depth(tmp_path):
    import mitsuba as mi
    path = scene_file(tmp_path, '<integrator type="volpath"><integer name="max_depth" value="3"/>'
                                '<integer name="rr_depth" value="2"/></integrator>' + LIT_SPHERE)
    ls = load_scene(path)
    assert ls.max_depth == 3 and ls.integrator_params == {"type": "volpath", "rr_depth": 2}
    assert "path" in str(ls.scene.integrator()).lower()
    path = scene_file(tmp_path, LIT_SPHERE, name="noint.xml")
    ls = load_scene(path)
    assert ls.max_depth is None and ls.integrator_params == {}
    assert isinstance(ls.scene.integrator(), mi.Integrator)


def test_integrator_max_depth_from_a_default_parameter(tmp_path):
    path = scene_file(tmp_path, '<default name="depth" value="6"/><integrator type="path">'
                                '<integer name="max_depth" value="$depth"/></integrator>' + LIT_SPHERE)
    assert load_scene(path).max_depth == 6


def test_take_integrator_keeps_depth_and_hidden_emitters_only():
    import xml.etree.ElementTree as ET
    from ppmrecon.render.scene import take_integrator
    root = ET.fromstring('<scene version="3.0.0"><integrator type="sppm"><integer name="maxDepth" value="65"/>'
                         '<boolean name="hideEmitters" value="true"/><integer name="photonCount" value="100"/>'
                         '<float name="initialRadius" value="0.01"/></integrator></scene>')
    max_depth, params = take_integrator(root)
    assert max_depth == 65 and params == {"type": "sppm", "photonCount": 100, "initialRadius": 0.01}
    (integ,) = root.findall("integrator")
    assert integ.get("type") == "path"
    assert {c.get("name"): c.get("value") for c in integ} == {"max_depth": "65", "hide_emitters": "true"}
