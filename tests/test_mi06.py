"""The Mitsuba 0.6 import layer: one test per rewrite of the table, refusal by name, and an
inline 0.6 scene with the literature scenes' constructs loading end to end."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest

from ppmrecon.render import mi06
from ppmrecon.render.scene import SceneError, load_scene


def run(rule: str, body: str) -> ET.Element:
    """Apply one rule of the table to ``<scene version="0.6.0">body</scene>``."""
    root = ET.fromstring(f'<scene version="0.6.0">{body}</scene>')
    mi06.rule_by_name(rule).apply(root, mi06.Context(label="t.xml"))
    return root


def floats(el: ET.Element) -> list[float]:
    return [float(v) for v in el.get("value").replace(",", " ").split()]


# --------------------------------------------------------------------------- the table itself

def test_table_is_documented_and_ordered():
    names = [r.name for r in mi06.RULES]
    assert names[0] == "known_constructs"          # refuse before rewriting anything
    assert len(names) == len(set(names))
    for r in mi06.RULES:
        assert len(r.doc) > 40, r.name
        assert "->" in r.doc, f"{r.name}: the docstring says what becomes what"


def test_every_rule_has_a_test():
    tested = {name[len("test_rule_"):] for name in globals() if name.startswith("test_rule_")}
    assert {r.name for r in mi06.RULES} <= tested


# --------------------------------------------------------------------------- one test per rule

def test_rule_known_constructs():
    for body, needle in [
        ('<shape type="sphere"><emitter type="area"><blackbody name="radiance" temperature="5000K"/></emitter></shape>',
         '<blackbody name="radiance">'),
        ('<bsdf type="roughdiffuse" id="r"/>', '<bsdf type="roughdiffuse" id="r">'),
        ('<shape type="heightfield"/>', '<shape type="heightfield">'),
        ('<include filename="other.xml"/>', "<include>"),
    ]:
        with pytest.raises(SceneError) as err:
            run("known_constructs", body)
        msg = str(err.value)
        assert msg.startswith("t.xml: Mitsuba 0.6 element ") and needle in msg, msg
        assert "not supported by the import layer" in msg and "\n" not in msg
    # integrator subtrees are exempt (any type); known constructs pass
    run("known_constructs", '<integrator type="sppm"><foo/></integrator><bsdf type="twosided">'
                            '<bsdf type="diffuse"/></bsdf>')


def test_rule_scene_version():
    assert run("scene_version", "").get("version") == "3.0.0"


def test_rule_integrator():
    root = run("integrator", '<integrator type="sppm"><integer name="maxDepth" value="5"/></integrator>')
    assert root.find("integrator") is not None  # left for the loader, untouched
    assert root.find("integrator/integer").get("name") == "maxDepth"
    with pytest.raises(SceneError, match=r'<integrator type="path"> inside <sensor'):
        run("integrator", '<sensor type="perspective"><integrator type="path"/></sensor>')


def test_rule_lookat_case():
    root = run("lookat_case", '<sensor type="perspective"><transform name="toWorld">'
                              '<lookAt origin="0,0,1" target="0,0,0" up="0,1,0"/></transform></sensor>')
    assert root.find("sensor/transform/lookat") is not None
    assert root.find("sensor/transform/lookAt") is None


def test_rule_srgb_to_rgb():
    root = run("srgb_to_rgb", '<bsdf type="diffuse"><srgb name="reflectance" value="0.94902 0.5 0.04045"/></bsdf>'
                              '<bsdf type="diffuse"><srgb name="reflectance" value="#ff8000"/></bsdf>'
                              '<bsdf type="diffuse"><srgb name="reflectance" value="1"/></bsdf>')
    a, b, c = root.findall("bsdf/rgb")
    assert a.get("name") == "reflectance" and root.find("bsdf/srgb") is None
    assert floats(a) == pytest.approx([0.88792, 0.21404, 0.04045 / 12.92], rel=1e-4)
    assert floats(b) == pytest.approx([1.0, 0.21586, 0.0], abs=1e-4)
    assert floats(c) == pytest.approx([1.0, 1.0, 1.0])


def test_rule_rgb_values():
    root = run("rgb_values", '<bsdf type="diffuse"><rgb name="reflectance" value="0.5" intent="reflectance"/></bsdf>'
                             '<bsdf type="diffuse"><rgb name="reflectance" value="#808080"/></bsdf>')
    a, b = root.findall("bsdf/rgb")
    assert floats(a) == [0.5, 0.5, 0.5] and "intent" not in a.attrib
    assert floats(b) == pytest.approx([0.21586] * 3, abs=1e-4)
    with pytest.raises(SceneError, match="needs 1 or 3 values"):
        run("rgb_values", '<rgb name="x" value="1 2"/>')


def test_rule_spectrum_values():
    root = run("spectrum_values",
               '<shape type="sphere"><emitter type="area"><spectrum name="radiance" value="31250"/></emitter></shape>'
               '<bsdf type="diffuse"><spectrum name="reflectance" value="360:0.5, 830:0.5"/></bsdf>')
    emit = root.find("shape/emitter/rgb")
    assert emit.get("name") == "radiance" and floats(emit) == [31250.0] * 3  # flat = white, not D65
    refl = root.find("bsdf/rgb")
    # a flat 0.5 over the visible range: 0.6's RGB mode gives 0.5 x (1.205, 0.948, 0.909)
    assert floats(refl) == pytest.approx([0.6024, 0.4741, 0.4546], abs=2e-3)
    with pytest.raises(SceneError, match="binned spectrum"):
        run("spectrum_values", '<spectrum name="x" value="0.1 0.2 0.3"/>')


def test_rule_param_renames():
    root = run("param_renames",
               '<sensor type="perspective"><string name="fovAxis" value="y"/><float name="nearClip" value="0.1"/>'
               '<float name="farClip" value="100"/><transform name="toWorld"/>'
               '<sampler type="independent"><integer name="sampleCount" value="4"/></sampler></sensor>'
               '<bsdf type="plastic"><float name="intIOR" value="1.5"/><float name="extIOR" value="1"/>'
               '<rgb name="specularReflectance" value="1"/><rgb name="diffuseReflectance" value="0.5"/></bsdf>'
               '<shape type="serialized"><integer name="shapeIndex" value="2"/><boolean name="faceNormals" value="true"/>'
               '<boolean name="flipNormals" value="true"/><float name="mysteryParam" value="1"/></shape>')
    names = {el.get("name") for el in root.iter() if el.get("name")}
    for new in ("fov_axis", "near_clip", "far_clip", "to_world", "sample_count", "int_ior", "ext_ior",
                "specular_reflectance", "diffuse_reflectance", "shape_index", "face_normals", "flip_normals"):
        assert new in names
    assert root.find("sensor/transform").get("name") == "to_world"
    assert "mysteryParam" in names  # unknown names are left for Mitsuba 3 to refuse by name


def test_rule_numeric_types():
    root = run("numeric_types", '<film type="hdrfilm"><float name="width" value="800.0"/>'
                                '<integer name="height" value="600"/></film>')
    w = root.find("film/integer[@name='width']")
    assert w is not None and w.get("value") == "800"
    with pytest.raises(SceneError, match="must be an integer"):
        run("numeric_types", '<film type="hdrfilm"><float name="width" value="800.5"/></film>')


@pytest.mark.parametrize("dist, expected", [("as", "beckmann"), ("phong", "beckmann"),
                                            ("ggx", "ggx"), ("beckmann", "beckmann")])
def test_rule_microfacet_distribution(dist, expected):
    root = run("microfacet_distribution", f'<bsdf type="roughconductor"><string name="distribution" value="{dist}"/>'
                                          '<float name="alpha" value="0.1"/></bsdf>')
    assert root.find("bsdf/string").get("value") == expected
    assert root.find("bsdf/float").get("value") == "0.1"


def test_rule_conductor_default_material():
    root = run("conductor_default_material", '<bsdf type="conductor"/><bsdf type="roughconductor">'
                                             '<string name="material" value="Ag"/></bsdf>')
    a, b = root.findall("bsdf")
    assert a.find("string[@name='material']").get("value") == "Cu"  # 0.6's default, not 3's "none"
    assert b.find("string[@name='material']").get("value") == "Ag"


def test_rule_conductor_ext_eta():
    root = run("conductor_ext_eta",
               '<bsdf type="conductor"><string name="material" value="none"/><string name="extEta" value="air"/></bsdf>'
               '<bsdf type="roughconductor"><float name="extEta" value="1"/><string name="material" value="Ag"/></bsdf>'
               '<bsdf type="conductor"><rgb name="eta" value="0.2, 0.9, 1.1"/><rgb name="k" value="3.9, 2.4, 2.1"/>'
               '<float name="extEta" value="1.333"/></bsdf>'
               '<bsdf type="conductor"><string name="material" value="Cu"/><string name="extEta" value="water"/></bsdf>')
    mirror, silver, explicit, copper = root.findall("bsdf")
    assert [c.get("name") for c in mirror] == ["material"]
    assert [c.get("name") for c in silver] == ["material"]
    assert floats(explicit.find("rgb[@name='eta']")) == pytest.approx([0.2 / 1.333, 0.9 / 1.333, 1.1 / 1.333], rel=1e-4)
    assert floats(explicit.find("rgb[@name='k']")) == pytest.approx([3.9 / 1.333, 2.4 / 1.333, 2.1 / 1.333], rel=1e-4)
    assert copper.find("string[@name='material']") is None
    eta = floats(copper.find("rgb[@name='eta']"))
    k = floats(copper.find("rgb[@name='k']"))
    assert len(eta) == 3 and len(k) == 3 and 0.1 < eta[0] < 0.3 and 2.0 < k[0] < 3.5  # Cu / 1.333
    with pytest.raises(SceneError, match="neither a number nor a known IOR name"):
        run("conductor_ext_eta", '<bsdf type="conductor"><string name="extEta" value="unobtainium"/></bsdf>')


def test_rule_sampler_types():
    root = run("sampler_types", '<sensor type="perspective"><sampler type="sobol"><integer name="sample_count" value="32"/>'
                                '<integer name="scramble" value="1"/></sampler></sensor>'
                                '<sensor type="perspective"><sampler type="ldsampler"><integer name="dimension" value="4"/>'
                                '</sampler></sensor>')
    a, b = root.findall("sensor/sampler")
    assert a.get("type") == b.get("type") == "independent"
    assert [c.get("name") for c in a] == ["sample_count"] and list(b) == []


def test_rule_film_options():
    root = run("film_options", '<sensor type="perspective"><film type="ldrfilm"><integer name="width" value="8"/>'
                               '<boolean name="banner" value="false"/><boolean name="highQualityEdges" value="false"/>'
                               '<boolean name="attachLog" value="false"/><string name="fileFormat" value="openexr"/>'
                               '<string name="pixelFormat" value="rgb"/><string name="componentFormat" value="float16"/>'
                               '<float name="exposure" value="1"/><rfilter type="gaussian"/></film></sensor>')
    film = root.find("sensor/film")
    assert film.get("type") == "hdrfilm"
    assert [c.get("name") or c.tag for c in film] == ["width", "rfilter"]


def test_rule_bitmap_options():
    root = run("bitmap_options",
               '<bsdf type="diffuse"><texture type="bitmap" name="reflectance"><string name="filename" value="a.png"/>'
               '<string name="filter_type" value="ewa"/><string name="wrapModeU" value="clamp"/>'
               '<string name="wrapModeV" value="clamp"/><float name="gamma" value="1"/>'
               '<float name="maxAnisotropy" value="20"/><boolean name="cache" value="true"/></texture></bsdf>'
               '<bsdf type="diffuse"><texture type="bitmap" name="reflectance"><string name="filename" value="b.png"/>'
               '<string name="filter_type" value="trilinear"/><float name="gamma" value="-1"/></texture></bsdf>')
    a, b = root.findall("bsdf/texture")
    pa = {c.get("name"): c.get("value") for c in a}
    assert pa == {"filename": "a.png", "filter_type": "bilinear", "wrap_mode": "clamp", "raw": "true"}
    pb = {c.get("name"): c.get("value") for c in b}
    assert pb == {"filename": "b.png", "filter_type": "bilinear"}
    with pytest.raises(SceneError, match="wrap mode 'zero'"):
        run("bitmap_options", '<texture type="bitmap"><string name="wrap_mode" value="zero"/></texture>')
    with pytest.raises(SceneError, match="gamma"):
        run("bitmap_options", '<texture type="bitmap"><float name="gamma" value="2.2"/></texture>')


def test_rule_texture_uv_transform():
    root = run("texture_uv_transform", '<texture type="checkerboard"><float name="uscale" value="4"/>'
                                       '<float name="voffset" value="0.5"/></texture>')
    tex = root.find("texture")
    assert [c.tag for c in tex] == ["transform"]
    tr = tex.find("transform")
    assert tr.get("name") == "to_uv"
    assert tr.find("scale").attrib == {"x": "4", "y": "1"}
    assert tr.find("translate").attrib == {"x": "0", "y": "0.5"}


def test_rule_spot_light():
    root = run("spot_light", '<emitter type="spot"><float name="cutoffAngle" value="30"/>'
                             '<float name="beamWidth" value="20"/><texture type="bitmap" name="texture">'
                             '<string name="filename" value="x.png"/></texture></emitter>')
    spot = root.find("emitter")
    assert [c.get("name") for c in spot] == ["cutoff_angle", "beam_width", "texture"]
    assert spot.find("texture").get("type") == "bitmap"
    with pytest.raises(SceneError, match="inside a spot light"):
        run("spot_light", '<emitter type="spot"><texture type="bitmap" name="pattern"/></emitter>')


def test_rule_mesh_options():
    root = run("mesh_options", '<shape type="obj"><string name="filename" value="a.obj"/>'
                               '<float name="maxSmoothAngle" value="0"/><boolean name="collapse" value="true"/></shape>'
                               '<shape type="serialized"><float name="maxSmoothAngle" value="30"/></shape>')
    a, b = root.findall("shape")
    assert {c.get("name"): c.get("value") for c in a} == {"filename": "a.obj", "face_normals": "true"}
    assert list(b) == []


def test_rule_shutter_time():
    root = run("shutter_time", '<sensor type="perspective"><float name="shutterOpen" value="0.5"/>'
                               '<float name="shutterOpenTime" value="2"/></sensor>')
    p = {c.get("name"): float(c.get("value")) for c in root.find("sensor")}
    assert p == {"shutter_open": 0.5, "shutter_close": 2.5}


def test_rule_references():
    run("references", '<bsdf type="diffuse" id="white"/><shape type="sphere"><ref id="white"/></shape>')
    with pytest.raises(SceneError, match="refers to id 'missing'"):
        run("references", '<shape type="sphere"><ref name="bsdf" id="missing"/></shape>')


def test_identical_constructs_pass_unchanged():
    """twosided, <ref>, matrix/rotate/scale transforms need no rule: the table leaves them alone."""
    body = ('<bsdf type="twosided" id="w"><bsdf type="diffuse"><rgb name="reflectance" value="0.5, 0.5, 0.5"/></bsdf></bsdf>'
            '<shape type="rectangle"><transform name="to_world"><scale x="2" y="1" z="1"/><rotate x="1" angle="90"/>'
            '<matrix value="1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1"/></transform><ref id="w"/></shape>')
    root = ET.fromstring(f'<scene version="0.6.0">{body}</scene>')
    mi06.translate(root, "t.xml")
    expected = ET.fromstring(f'<scene version="3.0.0">{body}</scene>')
    assert ET.tostring(root) == ET.tostring(expected)


# --------------------------------------------------------------------------- end to end

SCENE_06 = """<?xml version="1.0"?>
<scene version="0.6.0">
  <integrator type="sppm">
    <integer name="maxDepth" value="7"/>
    <integer name="photonCount" value="1000"/>
    <float name="initialRadius" value="0.05"/>
    <float name="alpha" value="0.7"/>
    <boolean name="hideEmitters" value="false"/>
  </integrator>
  <sensor type="perspective">
    <float name="fov" value="40"/>
    <string name="fovAxis" value="x"/>
    <float name="nearClip" value="0.01"/>
    <transform name="toWorld"><lookAt origin="0, 1, 4" target="0, 1, 0" up="0, 1, 0"/></transform>
    <sampler type="sobol"><integer name="sampleCount" value="8"/></sampler>
    <film type="hdrfilm">
      <integer name="width" value="32"/><integer name="height" value="24"/>
      <boolean name="banner" value="false"/><boolean name="attachLog" value="false"/>
      <boolean name="highQualityEdges" value="false"/><string name="pixelFormat" value="rgb"/>
      <rfilter type="gaussian"/>
    </film>
  </sensor>
  <bsdf type="twosided" id="floor"><bsdf type="roughconductor">
    <float name="alpha" value="0.1"/><string name="distribution" value="as"/>
    <float name="extEta" value="1"/><rgb name="specularReflectance" value="1, 1, 1"/>
    <string name="material" value="Ag"/></bsdf></bsdf>
  <bsdf type="diffuse" id="wall"><srgb name="reflectance" value="0.9 0.2 0.2"/></bsdf>
  <bsdf type="dielectric" id="glass"><string name="intIOR" value="bk7"/><string name="extIOR" value="air"/>
    <spectrum name="specularReflectance" value="0.9"/></bsdf>
  <bsdf type="conductor" id="metal"><string name="material" value="none"/><string name="extEta" value="air"/></bsdf>
  <shape type="rectangle"><transform name="toWorld"><scale x="2" y="2" z="1"/><rotate x="1" angle="-90"/></transform>
    <ref id="floor"/></shape>
  <shape type="rectangle"><transform name="toWorld"><scale x="2" y="2" z="1"/><translate z="-1.5"/></transform>
    <ref id="wall"/></shape>
  <shape type="sphere"><point name="center" x="0.5" y="0.4" z="0"/><float name="radius" value="0.4"/>
    <ref name="bsdf" id="glass"/></shape>
  <shape type="sphere"><point name="center" x="-0.5" y="0.4" z="0"/><float name="radius" value="0.4"/>
    <ref id="metal"/></shape>
  <shape type="rectangle"><transform name="toWorld"><scale x="0.2" y="0.2" z="1"/>
      <lookat origin="0, 2, 0" target="0, 0, 0" up="0, 0, 1"/></transform>
    <emitter type="area"><spectrum name="radiance" value="20"/><float name="samplingWeight" value="1"/></emitter></shape>
  <emitter type="spot">
    <transform name="toWorld"><lookat origin="0, 1, 3.5" target="0, 1, -1" up="0, -1, 0"/></transform>
    <float name="cutoffAngle" value="25"/>
    <texture type="bitmap" name="texture"><string name="filename" value="pattern.png"/>
      <string name="filterType" value="ewa"/></texture>
  </emitter>
</scene>
"""


@pytest.fixture
def scene06(tmp_path):
    from ppmrecon.render.scene import ensure_variant
    ensure_variant()
    import mitsuba as mi
    folder = tmp_path / "lit"
    folder.mkdir()
    img = np.zeros((8, 8, 3), np.uint8)
    img[:, :4, 0] = 255
    img[:4, :, 2] = 255
    mi.Bitmap(img).write(str(folder / "pattern.png"))
    (folder / "scene06.xml").write_text(SCENE_06)
    return folder / "scene06.xml"


def test_scene06_loads_and_renders(scene06, monkeypatch, tmp_path):
    import mitsuba as mi
    monkeypatch.chdir(tmp_path)  # relative files resolve against the scene's folder, not the cwd
    ls = load_scene(str(scene06))
    assert (ls.width, ls.height) == (32, 24)
    assert ls.max_depth == 7
    assert ls.integrator_params == {"type": "sppm", "photonCount": 1000, "initialRadius": 0.05, "alpha": 0.7}
    assert ls.source_version == "0.6.0"
    assert any("beckmann" in n for n in ls.notes)
    assert len(ls.scene.emitters()) == 2
    img = np.array(mi.render(ls.scene, spp=4))
    assert img.shape == (24, 32, 3) and np.isfinite(img).all() and img.max() > 0


def test_scene06_unknown_construct_is_refused_by_name(tmp_path):
    bad = SCENE_06.replace('<spectrum name="radiance" value="20"/>',
                           '<blackbody name="radiance" temperature="5000K"/>')
    path = tmp_path / "box.xml"
    path.write_text(bad)
    with pytest.raises(SceneError) as err:
        load_scene(str(path))
    msg = str(err.value)
    assert msg == (f'{path}: Mitsuba 0.6 element <blackbody name="radiance"> '
                   "is not supported by the import layer")


def test_scene06_unknown_parameter_is_named(scene06):
    bad = SCENE_06.replace('<float name="radius" value="0.4"/>', '<float name="radius" value="0.4"/>'
                           '<float name="wobbliness" value="2"/>', 1)
    path = scene06.with_name("x.xml")
    path.write_text(bad)
    with pytest.raises(SceneError) as err:
        load_scene(str(path))
    assert "wobbliness" in str(err.value) and "\n" not in str(err.value)
