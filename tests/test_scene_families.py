"""Imported scenes render what Mitsuba 3 renders: per plugin family a small generated
scene (Mitsuba 0.6 XML where 0.6 has the plugin), imported once, rendered by ppmrecon
(photons carry all light: ``direct="none"``) and by Mitsuba 3's ``path`` on the same
import; plus photon emission from every emitter the renderer samples, ``--check``, and
the import notes in the buffer header.

Budgets: 16x16 to 24x24 pixels, 2^15-2^16 photons x 16 passes, path at 256 spp.
Tolerances are stated per test; the figures measured when they were written are in
the docstrings.
"""

from __future__ import annotations

import numpy as np
import pytest

from ppmrecon.backend import choose_variant

choose_variant()

import mitsuba as mi  # noqa: E402

from ppmrecon import buffers as B  # noqa: E402
from ppmrecon.render.integrator import Renderer, RenderSettings  # noqa: E402
from ppmrecon.scene import load_scene  # noqa: E402

#: A 4x4 diffuse floor (rho 0.5) in the xz plane, seen from 0.9 above (60 degree fov):
#: the camera sees only the floor, so lights and the sky are never seen directly.
FLOOR06 = ('<shape type="rectangle"><transform name="toWorld"><scale value="4"/><rotate x="1" angle="-90"/>'
           '</transform><bsdf type="diffuse"><srgb name="reflectance" value="0.7354"/></bsdf></shape>')


def camera(version: str, res: int = 16, kind: str = "perspective", extra: str = "") -> str:
    tw = "toWorld" if version.startswith("0") else "to_world"
    la = "lookAt" if version.startswith("0") else "lookat"
    fov = '<float name="fov" value="60"/>' if kind != "orthographic" else ""
    return (f'<sensor type="{kind}">{fov}{extra}<transform name="{tw}">'
            + ('<scale x="0.5" y="0.5"/>' if kind == "orthographic" else "")
            + f'<{la} origin="0, 0.9, 0.01" target="0, 0, 0" up="0, 0, 1"/></transform>'
            f'<film type="hdrfilm"><integer name="width" value="{res}"/><integer name="height" value="{res}"/>'
            '</film></sensor>')


def write_scene(tmp_path, body: str, version: str = "0.6.0", name: str = "s.xml", **cam) -> str:
    path = tmp_path / name
    path.write_text(f'<scene version="{version}">{camera(version, **cam)}{body}</scene>')
    return str(path)


def both(path: str, passes: int = 16, photons: int = 1 << 16, spp: int = 256, max_depth: int = 2):
    """(ppmrecon's five estimates averaged, path's image, the loaded scene)."""
    ls = load_scene(path, warn=False)
    path_integrator = mi.load_dict({"type": "path", "max_depth": max_depth})
    ref = np.asarray(mi.render(ls.scene, integrator=path_integrator, spp=spp, seed=7), np.float64)
    res = Renderer(ls.scene, RenderSettings(passes=passes, photons=photons, seed=1, max_depth=max_depth,
                                            direct="none")).run()
    return res.estimates.astype(np.float64).mean(0), ref, ls


def pattern(path) -> None:
    px = np.zeros((8, 8, 3), np.uint8)
    px[::2, ::2] = 255
    px[1::2, 1::2] = 255
    mi.Bitmap(px).write(str(path))


def gradient_exr(path) -> None:
    mi.Bitmap(np.tile(np.linspace(0.2, 1.0, 8, dtype=np.float32)[None, :, None], (4, 1, 3))).write(str(path))


# --------------------------------------------------------------------------- emitters

EMITTERS06 = {
    "point": '<emitter type="point"><point name="position" x="0.3" y="1" z="0"/>'
             '<spectrum name="intensity" value="2"/></emitter>',
    "spot_textured": '<emitter type="spot"><transform name="toWorld"><lookAt origin="0, 1.5, 0" target="0, 0, 0" '
                     'up="0, 0, 1"/></transform><rgb name="intensity" value="4"/><float name="cutoffAngle" value="40"/>'
                     '<texture type="bitmap" name="texture"><string name="filename" value="pat.png"/></texture></emitter>',
    "directional": '<emitter type="directional"><vector name="direction" x="0.3" y="-1" z="0.2"/>'
                   '<blackbody name="irradiance" temperature="6500K" scale="2e-5"/></emitter>',
    "constant": '<emitter type="constant"><spectrum name="radiance" value="400:0.6, 700:0.8"/></emitter>',
    "envmap": '<emitter type="envmap"><string name="filename" value="env.exr"/><float name="scale" value="1.5"/></emitter>',
    "sunsky": '<emitter type="sunsky"><vector name="sunDirection" x="0.3" y="1" z="0.4"/>'
              '<float name="sunScale" value="0.5"/></emitter>',
    "sky": '<emitter type="sky"><float name="hour" value="10"/></emitter>',
    "sun": '<emitter type="sun"><vector name="sunDirection" x="-0.2" y="1" z="0.1"/></emitter>',
}
EMITTERS3 = {
    "area_textured": '<shape type="rectangle"><transform name="to_world"><scale value="0.5"/><rotate x="1" angle="90"/>'
                     '<translate y="1"/></transform><emitter type="area"><texture type="bitmap" name="radiance">'
                     '<string name="filename" value="pat.png"/></texture></emitter></shape>',
    "projector": '<emitter type="projector"><transform name="to_world"><lookat origin="0, 1.5, 0" target="0, 0, 0" '
                 'up="0, 0, 1"/></transform><float name="fov" value="40"/><float name="scale" value="3"/>'
                 '<texture type="bitmap" name="irradiance"><string name="filename" value="pat.png"/></texture></emitter>',
}


@pytest.mark.parametrize("name", sorted(EMITTERS06) + sorted(EMITTERS3))
def test_photons_from_every_emitter_match_path(tmp_path, name):
    """Mean floor radiance, photons only (max_depth 2: the light reaches the floor
    directly), over Mitsuba 3's path at 256 spp: within 5 %. Measured when written
    (2^16 photons x 16 passes): 0.98-1.02 for point, textured spot, directional,
    constant, envmap, sunsky, textured area light, projector. (0.6's collimated beam
    becomes a 0.05 degree spot: it lights a disc far smaller than a pixel, which path
    at 256 spp cannot resolve; its power is checked in test_mi06.)"""
    pattern(tmp_path / "pat.png")
    gradient_exr(tmp_path / "env.exr")
    if name in EMITTERS06:
        path = write_scene(tmp_path, FLOOR06 + EMITTERS06[name])
    else:
        floor3 = FLOOR06.replace("toWorld", "to_world").replace("<srgb", "<rgb").replace("0.7354", "0.5")
        path = write_scene(tmp_path, floor3 + EMITTERS3[name], version="3.0.0")
    ours, ref, ls = both(path)
    assert ref.mean() > 0
    assert ours.mean() / ref.mean() == pytest.approx(1.0, abs=0.05), (ours.mean(), ref.mean())
    if name in ("sunsky", "sky", "sun"):
        assert any("'sunsky'" in n for n in ls.notes)


def test_emitter_texture_that_cannot_be_sampled_is_refused(tmp_path):
    body = ('<shape type="rectangle"><emitter type="area"><texture type="checkerboard" name="radiance"/>'
            '</emitter></shape>')
    path = write_scene(tmp_path, body, version="3.0.0")
    with pytest.raises(Exception) as err:
        load_scene(path)
    msg = str(err.value)
    assert "\n" not in msg and "'checkerboard' texture cannot be sampled for photon emission" in msg
    assert msg.startswith(f"{path}:1: <emitter type=\"area\">")


# --------------------------------------------------------------------------- BSDFs, textures, shapes, sensors

def tiles(bsdfs: list[str], version: str = "0.6.0") -> str:
    """Floor tiles side by side along x (one per BSDF), each 2/n wide, 2 deep."""
    n = len(bsdfs)
    tw = "toWorld" if version.startswith("0") else "to_world"
    out = []
    for i, b in enumerate(bsdfs):
        x = -1 + (2 * i + 1) / n
        out.append(f'<shape type="rectangle"><transform name="{tw}"><scale x="{1 / n}" y="1"/>'
                   f'<rotate x="1" angle="-90"/><translate x="{x}"/></transform>{b}</shape>')
    return "".join(out)


LIGHTS06 = ('<emitter type="point"><point name="position" x="0.2" y="0.8" z="0.3"/><spectrum name="intensity" value="1"/>'
            '</emitter><emitter type="constant"><spectrum name="radiance" value="0.3"/></emitter>')


def compare_tiles(tmp_path, bsdfs: list[str], res: int = 32, body: str = "", tol: float = 0.06,
                  version: str = "0.6.0", **cam):
    """Render tiles of ``bsdfs`` (at most 4: 8 pixels a tile) by ppmrecon (2^15 photons x
    32 passes) and path (512 spp); per-tile mean ratio within ``tol``, whole image 3 %."""
    lights = LIGHTS06 if version.startswith("0") else LIGHTS06.replace("spectrum", "rgb")
    path = write_scene(tmp_path, tiles(bsdfs, version) + lights + body, version=version, res=res, **cam)
    ours, ref, ls = both(path, photons=1 << 15, passes=32, spp=512)
    cols = np.array_split(np.arange(res), len(bsdfs))
    # the camera looks down -y with up +z: image x runs along -x of the world
    ratios = [ours[:, c].mean() / ref[:, c].mean() for c in cols[::-1]]
    assert ours.mean() / ref.mean() == pytest.approx(1.0, abs=0.03), ratios
    assert all(r == pytest.approx(1.0, abs=tol) for r in ratios), ratios
    return ls, ratios


BSDFS06 = [
    '<bsdf type="roughdiffuse"><rgb name="reflectance" value="0.6"/></bsdf>',
    '<bsdf type="phong"><float name="exponent" value="20"/></bsdf>',
    '<bsdf type="ward"><float name="alphaU" value="0.1"/><float name="alphaV" value="0.3"/></bsdf>',
    '<bsdf type="coating"><bsdf type="roughconductor"><string name="distribution" value="as"/>'
    '<float name="alphaU" value="0.2"/><float name="alphaV" value="0.3"/></bsdf></bsdf>',
    '<bsdf type="roughcoating"><bsdf type="diffuse"/></bsdf>',
    '<bsdf type="mixturebsdf"><string name="weights" value="0.3, 0.6"/><bsdf type="diffuse"/>'
    '<bsdf type="roughplastic"><float name="alpha" value="0.3"/></bsdf></bsdf>',
    '<bsdf type="bumpmap"><texture type="scale"><float name="scale" value="0.5"/><texture type="bitmap">'
    '<string name="filename" value="h.png"/></texture></texture><bsdf type="diffuse"/></bsdf>',
    '<bsdf type="twosided"><bsdf type="blendbsdf"><float name="weight" value="0.4"/><bsdf type="diffuse"/>'
    '<bsdf type="roughconductor"><string name="material" value="Au"/><float name="alpha" value="0.3"/></bsdf>'
    '</bsdf></bsdf>',
]


@pytest.mark.parametrize("group", [0, 1])
def test_bsdf_family_matches_path(tmp_path, group):
    """0.6 BSDFs, imported, each on a floor tile under a point light and a constant sky:
    per-tile ppmrecon / path within 6 %, whole image 3 % (measured when written at 64
    passes: 0.977-1.006 per tile, 0.995 whole)."""
    write_height(tmp_path / "h.png")
    ls, _ = compare_tiles(tmp_path, BSDFS06[4 * group:4 * group + 4])
    kinds = " ".join(ls.notes)
    for kind in (("roughdiffuse", "phong", "ward", "coating"), ("roughcoating", "bumpmap"))[group]:
        assert f'type="{kind}"' in kinds, kind


def write_height(path) -> None:
    x = np.linspace(0, 4 * np.pi, 32)
    h = (0.5 + 0.5 * np.sin(x)[None, :] * np.cos(x)[:, None]) * 255
    mi.Bitmap(np.repeat(h[..., None], 3, -1).astype(np.uint8)).write(str(path))


def write_colored_ply(path) -> None:
    """A 2x2 square in the xy plane whose four vertices carry red, green, blue, white."""
    verts = [(-1, -1, 0, 255, 0, 0), (1, -1, 0, 0, 255, 0), (1, 1, 0, 0, 0, 255), (-1, 1, 0, 255, 255, 255)]
    head = ("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
            "property uchar red\nproperty uchar green\nproperty uchar blue\nelement face 2\n"
            "property list uchar int vertex_indices\nend_header\n")
    path.write_text(head + "".join(" ".join(map(str, v)) + "\n" for v in verts) + "3 0 1 2\n3 0 2 3\n")


def test_texture_family_matches_path(tmp_path):
    """0.6 textures on diffuse tiles: per-tile ppmrecon / path within 6 %."""
    px = np.zeros((4, 4, 4), np.uint8)
    px[..., 0], px[..., 3] = 200, 120
    mi.Bitmap(px, mi.Bitmap.PixelFormat.RGBA).write(str(tmp_path / "rgba.png"))
    write_colored_ply(tmp_path / "tile.ply")
    ply = ('<shape type="ply"><string name="filename" value="tile.ply"/><transform name="toWorld">'
           '<scale x="0.25" y="1" z="1"/><rotate x="1" angle="-90"/><translate x="-0.75" y="0.001"/></transform>'
           '<bsdf type="diffuse"><texture type="vertexcolors" name="reflectance"/></bsdf></shape>')
    compare_tiles(tmp_path, [
        '<bsdf type="diffuse"><texture type="bitmap" name="reflectance"><string name="filename" value="rgba.png"/>'
        '<string name="channel" value="a"/><float name="gamma" value="2.2"/><string name="filterType" value="ewa"/>'
        '</texture></bsdf>',
        '<bsdf type="diffuse"><texture type="checkerboard" name="reflectance"><float name="uscale" value="4"/>'
        '<float name="vscale" value="4"/><srgb name="color0" value="#c0c0c0"/></texture></bsdf>',
        '<bsdf type="diffuse"><texture type="gridtexture" name="reflectance"><float name="lineWidth" value="0.1"/>'
        '<rgb name="color1" value="0.9"/></texture></bsdf>',
        '<bsdf type="diffuse"><texture type="scale" name="reflectance"><float name="scale" value="0.5"/>'
        '<texture type="bitmap"><string name="filename" value="rgba.png"/></texture></texture></bsdf>',
    ], body=ply)


def test_shape_family_matches_path(tmp_path):
    """0.6 shapes on the floor (sphere, cylinder, disk, cube, OBJ, a shapegroup instanced
    twice), lit from above: whole-image ppmrecon / path within 5 % (max_depth 3)."""
    (tmp_path / "tri.obj").write_text("v -0.3 0 -0.3\nv 0.3 0 -0.3\nv 0 0 0.3\nf 1 2 3\n")
    body = (FLOOR06 + LIGHTS06 +
            '<shape type="sphere"><point name="center" x="-0.3" y="0.1" z="0.2"/><float name="radius" value="0.1"/></shape>'
            '<shape type="cylinder"><point name="p0" x="0.3" y="0" z="0"/><point name="p1" x="0.3" y="0.2" z="0"/>'
            '<float name="radius" value="0.05"/></shape>'
            '<shape type="disk"><transform name="toWorld"><scale value="0.1"/><rotate x="1" angle="-90"/>'
            '<translate x="0.1" y="0.05" z="-0.3"/></transform></shape>'
            '<shape type="cube"><transform name="toWorld"><scale value="0.05"/><translate x="-0.2" y="0.05" z="-0.2"/>'
            '</transform></shape>'
            '<shape type="obj"><string name="filename" value="tri.obj"/><transform name="toWorld">'
            '<translate y="0.02"/></transform></shape>'
            '<shape type="shapegroup" id="g"><shape type="sphere"><float name="radius" value="0.04"/></shape></shape>'
            '<shape type="instance"><ref id="g"/><transform name="toWorld"><translate x="0.2" y="0.04" z="0.3"/>'
            '</transform></shape>'
            '<shape type="instance"><ref id="g"/><transform name="toWorld"><translate x="-0.1" y="0.04" z="0.35"/>'
            '</transform></shape>')
    ours, ref, ls = both(write_scene(tmp_path, body, res=24), photons=1 << 15, max_depth=3)
    assert ours.mean() / ref.mean() == pytest.approx(1.0, abs=0.05)
    assert len(ls.scene.shapes()) >= 8


@pytest.mark.parametrize("kind, extra", [("thinlens", '<float name="apertureRadius" value="0.01"/>'
                                                     '<float name="focusDistance" value="0.9"/>'),
                                         ("orthographic", "")])
def test_sensor_family_matches_path(tmp_path, kind, extra):
    """0.6 thinlens and orthographic sensors: whole-image ppmrecon / path within 5 %."""
    path = write_scene(tmp_path, FLOOR06 + LIGHTS06, kind=kind, extra=extra)
    ours, ref, _ = both(path, photons=1 << 15)
    assert ours.mean() / ref.mean() == pytest.approx(1.0, abs=0.05)


# --------------------------------------------------------------------------- one of each, --check, header

ONE_OF_EACH = """<scene version="0.6.0">
  <default name="res" value="12"/>
  <integrator type="sppm"><integer name="maxDepth" value="4"/></integrator>
  <sensor type="perspective"><float name="fov" value="60"/>
    <transform name="toWorld"><lookAt origin="0, 0.9, 0.01" target="0, 0, 0" up="0, 0, 1"/></transform>
    <sampler type="ldsampler"><integer name="sampleCount" value="4"/></sampler>
    <film type="ldrfilm"><integer name="width" value="$res"/><integer name="height" value="$res"/>
      <boolean name="banner" value="false"/></film></sensor>
  <include filename="materials.xml"/>
  <shape type="rectangle"><transform name="toWorld"><scale value="2"/><rotate x="1" angle="-90"/></transform>
    <ref id="floor"/></shape>
  <shape type="sphere"><point name="center" x="0" y="0.15" z="0"/><float name="radius" value="0.1"/>
    <bsdf type="dielectric"/></shape>
  <emitter type="sunsky"><vector name="sunDirection" x="0" y="1" z="0.5"/></emitter>
  <shape type="disk"><transform name="toWorld"><scale value="0.1"/><rotate x="1" angle="90"/>
    <translate y="1.2"/></transform><emitter type="area"><blackbody name="radiance" temperature="3000K" scale="1e-3"/>
    </emitter></shape>
</scene>"""
MATERIALS = """<scene version="0.6.0">
  <bsdf type="phong" id="floor"><spectrum name="diffuseReflectance" value="0.2, 0.3, 0.4, 0.5"/></bsdf>
</scene>"""


def one_of_each(tmp_path):
    (tmp_path / "materials.xml").write_text(MATERIALS)
    path = tmp_path / "all.xml"
    path.write_text(ONE_OF_EACH)
    return path


def test_one_element_of_each_family_loads_and_renders(tmp_path):
    ls = load_scene(str(one_of_each(tmp_path)), warn=False)
    assert (ls.width, ls.height, ls.max_depth) == (12, 12, 4)
    res = Renderer(ls.scene, RenderSettings(passes=2, photons=1 << 12, seed=0, max_depth=4)).run()
    assert np.isfinite(res.estimates).all() and res.estimates.mean() > 0
    joined = "\n".join(ls.notes)
    for needle in ('type="phong"', 'type="sunsky"', "spectral bins", "ldsampler", "ldrfilm"):
        assert needle in joined, needle
    assert f'{tmp_path / "materials.xml"}:2: <bsdf type="phong" id="floor">' in joined   # the included file's line


def test_check_reports_and_does_not_render(tmp_path, capsys):
    from ppmrecon.render.cli import main
    path = one_of_each(tmp_path)
    out = tmp_path / "never.exr"
    assert main([str(path), "--check", "-o", str(out)]) == 0
    text = capsys.readouterr()
    assert not out.exists()
    assert text.out.startswith(f"{path}: loaded (scene version 0.6.0), 12x12, max_depth 4")
    assert "SunskyEmitter" in text.out and 'type="phong"' in text.out
    assert "warning" not in text.err     # --check reports on stdout once


def test_render_warns_and_writes_notes_into_the_header(tmp_path, capsys):
    from ppmrecon.render.cli import main
    path = one_of_each(tmp_path)
    out = tmp_path / "r.exr"
    assert main([str(path), "--passes", "1", "--photons", "256", "-q", "-o", str(out)]) == 0
    ls = load_scene(str(path), warn=False)
    warnings = [line for line in capsys.readouterr().err.splitlines() if "scene import" in line]
    assert len(warnings) == len(ls.notes) > 0
    assert B.decode_notes(B.read_buffers(out).header) == ls.notes


def test_mitsuba3_native_bsdfs_render(tmp_path):
    """Mitsuba 3 scenes with principled, normalmap, bumpmap and blendbsdf tiles render
    what path renders (per tile within 6 %, whole image 3 %)."""
    write_height(tmp_path / "h.png")
    normal = np.zeros((8, 8, 3), np.uint8)
    normal[..., 0], normal[..., 1], normal[..., 2] = 150, 128, 230
    mi.Bitmap(normal).write(str(tmp_path / "n.png"))
    bsdfs = [
        '<bsdf type="principled"><rgb name="base_color" value="0.6, 0.4, 0.3"/><float name="roughness" value="0.4"/>'
        '<float name="metallic" value="0.3"/></bsdf>',
        '<bsdf type="normalmap"><texture type="bitmap" name="normalmap"><string name="filename" value="n.png"/>'
        '<boolean name="raw" value="true"/></texture><bsdf type="diffuse"/></bsdf>',
        '<bsdf type="bumpmap"><texture type="bitmap"><string name="filename" value="h.png"/>'
        '<boolean name="raw" value="true"/></texture><float name="scale" value="0.5"/><bsdf type="diffuse"/></bsdf>',
        '<bsdf type="blendbsdf"><float name="weight" value="0.3"/><bsdf type="diffuse"/>'
        '<bsdf type="roughconductor"/></bsdf>',
    ]
    compare_tiles(tmp_path, bsdfs[:4], version="3.0.0")


def test_mask_lets_the_eye_through(tmp_path):
    """A Mitsuba 3 mask (opacity 0.3) over nothing but the sky: the eye path passes with
    probability 0.7 and sees the sky, else gathers; ppmrecon / path within 4 % (1.003
    measured; gathering at the mask alone gives about 0.5)."""
    floor = FLOOR06.replace("toWorld", "to_world").replace(
        '<bsdf type="diffuse"><srgb name="reflectance" value="0.7354"/></bsdf>',
        '<bsdf type="mask"><float name="opacity" value="0.3"/><bsdf type="diffuse"/></bsdf>')
    path = write_scene(tmp_path, floor + LIGHTS06.replace("spectrum", "rgb"), version="3.0.0")
    ours, ref, _ = both(path, photons=1 << 15, max_depth=-1)
    assert ours.mean() / ref.mean() == pytest.approx(1.0, abs=0.04)


def test_hair_bsdf_is_refused(tmp_path):
    path = write_scene(tmp_path, '<shape type="sphere"><bsdf type="hair"/></shape>', version="3.0.0")
    with pytest.raises(Exception, match=r"<bsdf type=\"hair\">: .*not supported by the ppmrecon renderer"):
        load_scene(path)
