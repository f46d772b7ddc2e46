"""Scene loading for the renderer: built-in scenes, Mitsuba 3 XML and Mitsuba 0.6 XML.

``load_scene(spec)`` turns a scene argument (None, a built-in name, or a path) into a
loaded ``mi.Scene`` plus what the renderer needs to know about the file: the film size,
the path-depth limit, the parameters of the file's own integrator element and the
import notes (what was approximated). The renderer is ours, so the file's integrator is
never used for rendering; it is replaced by a Mitsuba 3 ``path`` integrator with the
same ``max_depth`` so that ``mi.render`` still gives a comparable reference image.

Mitsuba 0.6 files (root ``<scene version="0.x">``) go through :mod:`.mi06` first, with
``<include>`` files and line numbers. Whatever the renderer does not simulate
(participating media, emitter or sensor types it cannot sample, Mitsuba 3 BSDFs it
cannot trace) is refused with a one-line :class:`SceneError` that names the element,
before Mitsuba sees the file. Each note is printed as a warning line at load.
"""

from __future__ import annotations

import hashlib
import os
import re
import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

from ..data import SCENES
from .common import (Context, Lines, SceneError, describe, ensure_variant, mitsuba_error_line,
                     parse_xml)

if TYPE_CHECKING:  # pragma: no cover
    import mitsuba as mi

DEFAULT_SCENE = "cornell_caustics"
#: The built-in scenes travel inside the package (ppmrecon/data/scenes).
SCENES_DIR = SCENES

#: Emitters the photon pass samples, each checked by an energy test against Mitsuba 3's
#: `path` (tests/test_scene_families.py). `directionalarea` samples rays too, but `path`
#: cannot see it (a delta direction on a surface), so nothing could check it.
SUPPORTED_EMITTERS = ("area", "point", "spot", "directional", "envmap", "constant", "sunsky", "projector")
SUPPORTED_SENSORS = ("perspective", "thinlens", "orthographic")
MEDIUM_TAGS = ("medium", "phase", "subsurface")
# Property names whose value is a file, resolved against the scene file's folder.
FILE_PARAMS = ("filename",)
_MAX_DEPTH_NAMES = ("max_depth", "maxDepth")
_HIDE_NAMES = ("hide_emitters", "hideEmitters")
_PROPERTY_TAGS = ("integer", "float", "boolean", "string")
#: Emitters whose texture photon emission samples (Texture::sample_spectrum), and the
#: Mitsuba 3 textures that implement it in RGB mode.
_SAMPLED_EMITTER_TEXTURES = ("area", "spot")
SAMPLEABLE_TEXTURES = ("bitmap",)
#: Mitsuba 3 BSDFs the renderer refuses, and why.
REFUSED_BSDFS = {"hair": "it models fibres of curve shapes; its photon estimate on surfaces was 7 % off `path`"}


@dataclass
class LoadedScene:
    """A loaded scene and what the renderer needs from its file."""

    scene: "mi.Scene"
    name: str
    path: Path | None
    width: int
    height: int
    max_depth: int | None  # from the file's integrator (maxDepth / max_depth), if any
    integrator_params: dict[str, Any]  # the file integrator's other params (+ "type"), for information
    source_version: str = "3.0.0"  # the file's <scene version>; 0.x went through mi06
    notes: list[str] = field(default_factory=list)  # lossy or noteworthy translations (0.6 files)
    #: SHA-256 of the scene as written (the parsed XML before any rewriting), of the files
    #: it includes and of every file it references: a saved render state is tied to it
    #: (see ppmrecon.render.state).
    content_hash: str = ""

    @property
    def label(self) -> str:
        return str(self.path) if self.path is not None else self.name

    def depths(self) -> tuple[int, int]:
        """(max_depth, rr_depth) of the file's integrator, Mitsuba's convention: max_depth
        counts the segments of a whole camera-to-light path, -1 (Mitsuba's default when
        the file names none) is unbounded; rr_depth defaults to Mitsuba's 5."""
        max_depth = -1 if self.max_depth is None else int(self.max_depth)
        if max_depth == 0 or max_depth < -1:
            raise SceneError(f"{self.label}: integrator max_depth {max_depth}: must be positive or -1 (unbounded)")
        rr = next((self.integrator_params[k] for k in ("rr_depth", "rrDepth") if k in self.integrator_params), 5)
        try:
            rr_depth = int(rr)
        except (TypeError, ValueError):
            raise SceneError(f"{self.label}: integrator rr_depth '{rr}' is not an integer") from None
        if rr_depth <= 0:
            raise SceneError(f"{self.label}: integrator rr_depth {rr_depth}: must be positive")
        return max_depth, rr_depth


def builtin_scenes() -> dict[str, Path]:
    """Built-in scene names -> XML paths (every ``ppmrecon/data/scenes/*.xml``)."""
    if not SCENES_DIR.is_dir():
        return {}
    return {p.stem: p for p in sorted(SCENES_DIR.glob("*.xml"))}


# --------------------------------------------------------------------------- helpers

def parse_version(text: str | None, label: str) -> tuple[int, ...]:
    """``"0.6.0"`` -> ``(0, 6, 0)``; SceneError when missing or malformed."""
    if text is None:
        raise SceneError(f"{label}: the root <scene> element has no version attribute "
                         "(Mitsuba 3 needs version=\"3.0.0\"; Mitsuba 0.6 files have version=\"0.6.0\")")
    try:
        return tuple(int(p) for p in text.strip().split("."))
    except ValueError:
        raise SceneError(f"{label}: unreadable scene version '{text}'") from None


def _value(el: ET.Element, defaults: dict[str, str] | None = None) -> Any:
    """Python value of a property element (integer/float/boolean/string), else its value
    text; ``$name`` values are looked up in the file's ``<default>`` elements."""
    v = el.get("value")
    if v is None:
        return None
    if v.startswith("$") and defaults and v[1:] in defaults:
        v = defaults[v[1:]]
    try:
        if el.tag == "integer":
            return int(v)
        if el.tag == "float":
            return float(v)
        if el.tag == "boolean":
            return v.strip().lower() in ("true", "1", "yes")
    except ValueError:
        return v
    return v


def _parent_map(root: ET.Element) -> dict[ET.Element, ET.Element]:
    return {c: p for p in root.iter() for c in p}


# --------------------------------------------------------------------------- checks

def refuse_unsupported(root: ET.Element, label: str, lines: Lines | None = None) -> None:
    """Refuse what the renderer does not simulate, naming the element and, where the
    file gave it, its line (both dialects)."""
    ids = {el.get("id"): el for el in root.iter() if el.get("id") is not None and el.tag != "ref"}
    for el in root.iter():
        where = f"{lines[el][0]}:{lines[el][1]}" if lines and el in lines else label
        if el.tag in MEDIUM_TAGS:
            raise SceneError(f"{where}: {describe(el)}: participating media are not simulated "
                             "by the ppmrecon renderer")
        if el.tag == "ref" and el.get("name") in ("interior", "exterior"):
            raise SceneError(f"{where}: {describe(el)}: shapes with interior/exterior media are not "
                             "simulated by the ppmrecon renderer")
        if el.tag == "emitter" and el.get("type") not in SUPPORTED_EMITTERS:
            raise SceneError(f"{where}: {describe(el)}: emitter type '{el.get('type')}' is not supported "
                             f"by the ppmrecon renderer (supported: {', '.join(SUPPORTED_EMITTERS)})")
        if el.tag == "emitter" and el.get("type") in _SAMPLED_EMITTER_TEXTURES:
            for tex in el:
                if tex.tag == "ref":
                    tex = ids.get(tex.get("id"), tex)
                if tex.tag == "texture" and tex.get("type") not in SAMPLEABLE_TEXTURES:
                    raise SceneError(f"{where}: {describe(el)}: its '{tex.get('type')}' texture cannot be sampled "
                                     "for photon emission (Mitsuba 3 implements sample_spectrum for "
                                     f"{', '.join(SAMPLEABLE_TEXTURES)} textures only)")
        if el.tag == "bsdf" and el.get("type") in REFUSED_BSDFS:
            raise SceneError(f"{where}: {describe(el)}: BSDF type '{el.get('type')}' is not supported by the "
                             f"ppmrecon renderer ({REFUSED_BSDFS[el.get('type')]})")
        if el.tag == "sensor" and el.get("type") not in SUPPORTED_SENSORS:
            raise SceneError(f"{where}: {describe(el)}: sensor type '{el.get('type')}' is not supported "
                             f"by the ppmrecon renderer (supported: {', '.join(SUPPORTED_SENSORS)})")


# --------------------------------------------------------------------------- integrator

def take_integrator(root: ET.Element) -> tuple[int | None, dict[str, Any]]:
    """Remove the file's integrator element(s), return (max_depth, other params), and put
    a Mitsuba 3 ``path`` integrator with that max_depth (and hide_emitters) in their place.

    Nested integrators (0.6 ``adaptive``/``irrcache`` wrappers, 3.x ``aov``) are
    flattened: the outermost type is ``type``, inner types are listed in ``inner_types``.
    """
    found = [el for el in root if el.tag == "integrator"]
    defaults = _defaults(root)
    max_depth: int | None = None
    hide: bool | None = None
    params: dict[str, Any] = {}
    for top in found:
        for integ in top.iter("integrator"):
            if integ is top:
                params.setdefault("type", integ.get("type"))
            else:
                params.setdefault("inner_types", []).append(integ.get("type"))
            for prop in integ:
                if prop.tag not in _PROPERTY_TAGS or prop.get("name") is None:
                    continue
                name, value = prop.get("name"), _value(prop, defaults)
                if name in _MAX_DEPTH_NAMES and max_depth is None:
                    try:
                        max_depth = int(value)
                    except (TypeError, ValueError):
                        pass
                elif name in _HIDE_NAMES:
                    hide = bool(value)
                else:
                    params.setdefault(name, value)
        root.remove(top)
    path = ET.Element("integrator", {"type": "path"})
    if max_depth is not None:
        ET.SubElement(path, "integer", {"name": "max_depth", "value": str(max_depth)})
    if hide is not None:
        ET.SubElement(path, "boolean", {"name": "hide_emitters", "value": str(hide).lower()})
    path.tail = "\n"
    root.insert(0, path)
    return max_depth, params


# --------------------------------------------------------------------------- resolution

def _defaults(root: ET.Element) -> dict[str, str]:
    return {d.get("name"): d.get("value") for d in root.iter("default") if d.get("name")}


def _int_param(film: ET.Element, name: str, defaults: dict[str, str], label: str) -> int | None:
    for prop in film:
        if prop.get("name") == name and prop.tag in ("integer", "float"):
            text = prop.get("value", "")
            if text.startswith("$"):
                text = defaults.get(text[1:], text)
            try:
                return int(float(text))
            except ValueError:
                raise SceneError(f"{label}: film {name} '{prop.get('value')}' is not a number") from None
    return None


def _set_int(film: ET.Element, name: str, value: int) -> None:
    for prop in list(film):
        if prop.get("name") == name and prop.tag in ("integer", "float", "string"):
            film.remove(prop)
    el = ET.Element("integer", {"name": name, "value": str(int(value))})
    el.tail = "\n"
    film.insert(0, el)


def apply_resolution(root: ET.Element, resolution: tuple[int, int] | int | None, label: str) -> None:
    """Override the film size of every sensor: (W, H), or W alone keeping the aspect ratio.

    A crop window, if any, no longer matches the new size and is removed.
    """
    if resolution is None:
        return
    if isinstance(resolution, (tuple, list)):
        if len(resolution) != 2:
            raise SceneError(f"{label}: resolution must be (width, height) or a width, got {resolution!r}")
        want_w, want_h = resolution
    else:
        want_w, want_h = resolution, None
    for v in (want_w, want_h):
        if v is not None and (not isinstance(v, (int,)) or isinstance(v, bool) or v < 1):
            raise SceneError(f"{label}: resolution must be positive integers, got {resolution!r}")
    defaults = _defaults(root)
    sensors = [s for s in root.iter("sensor")]
    if not sensors:
        raise SceneError(f"{label}: no <sensor> in the scene; cannot set the resolution")
    for sensor in sensors:
        film = sensor.find("film")
        if film is None:
            film = ET.SubElement(sensor, "film", {"type": "hdrfilm"})
        # Mitsuba's default film size is 768 x 576, in both dialects.
        w = _int_param(film, "width", defaults, label) or 768
        h = _int_param(film, "height", defaults, label) or 576
        new_h = want_h if want_h is not None else max(1, round(want_w * h / w))
        _set_int(film, "width", want_w)
        _set_int(film, "height", new_h)
        for prop in list(film):
            if prop.get("name", "").replace("_", "").lower().startswith("crop"):
                film.remove(prop)


# --------------------------------------------------------------------------- files

def check_files(root: ET.Element, folder: Path, label: str) -> None:
    """Every relative ``filename`` must exist next to the scene file (or be absolute and
    exist); say which element wants which file when one is missing."""
    parents = _parent_map(root)
    defaults = _defaults(root)
    for el in root.iter("string"):
        if el.get("name") not in FILE_PARAMS:
            continue
        value = el.get("value", "")
        if value.startswith("$"):
            value = defaults.get(value[1:], value)
        if "$" in value:
            continue  # substituted by Mitsuba at load time; let it report problems
        target = Path(value) if os.path.isabs(value) else folder / value
        if not target.exists():
            owner = parents.get(el)
            what = describe(owner) if owner is not None else "<scene>"
            raise SceneError(f"{label}: {what} refers to '{value}', which does not exist "
                             f"(looked in {target.parent})")


class _ResolverScope:
    """Prepend a folder to Mitsuba's file resolver for the duration of a load, then
    restore it, so relative references resolve against the scene file's folder without
    leaking into later loads."""

    def __init__(self, folder: Path | None):
        self.folder = folder
        self.saved: list[str] | None = None

    def __enter__(self) -> "_ResolverScope":
        if self.folder is None:
            return self
        import mitsuba as mi
        fr = mi.file_resolver() if hasattr(mi, "file_resolver") else mi.Thread.thread().file_resolver()
        self.fr = fr
        self.saved = [str(fr[i]) for i in range(len(fr))]
        fr.prepend(str(self.folder))
        return self

    def __exit__(self, *exc: object) -> None:
        if self.saved is None:
            return
        self.fr.clear()
        for p in self.saved:
            self.fr.append(p)


def _absolutise_files(root: ET.Element, folder: Path) -> None:
    """Rewrite relative ``filename`` values to absolute paths in the scene's folder:
    Mitsuba may instantiate plugins on worker threads, and the tree is loaded from a
    string, so nothing else ties a relative name to the scene file's folder."""
    for el in root.iter("string"):
        if el.get("name") in FILE_PARAMS:
            value = el.get("value", "")
            if value and not value.startswith("$") and not os.path.isabs(value) and (folder / value).exists():
                el.set("value", str((folder / value).resolve()))


def _hash_referenced_files(root: ET.Element, digest: "hashlib._Hash") -> None:
    """Feed the bytes of every existing file the (absolutised) tree references into
    ``digest``, in document order: a changed mesh or texture changes the scene."""
    from ..fileio import file_sha256

    for el in root.iter("string"):
        value = el.get("value", "")
        if el.get("name") in FILE_PARAMS and os.path.isabs(value) and os.path.isfile(value):
            digest.update(file_sha256(value).encode())


def _hash_included_files(root: ET.Element, folder: Path | None, digest: "hashlib._Hash") -> None:
    """Feed the bytes of the files a 0.6 ``<include>`` names (before the import inlines them)."""
    from ..fileio import file_sha256

    for el in root.iter("include"):
        name = el.get("filename", "")
        target = Path(name) if os.path.isabs(name) or folder is None else folder / name
        if target.is_file():
            digest.update(file_sha256(target).encode())


# --------------------------------------------------------------------------- load

def _resolve_spec(spec: str | os.PathLike | None) -> tuple[str, Path, bool]:
    """(name, path, is_builtin) for a scene argument."""
    builtins = builtin_scenes()
    if spec is None:
        spec = DEFAULT_SCENE
    text = os.fspath(spec)
    if text in builtins:
        return text, builtins[text], True
    path = Path(text).expanduser()
    if path.is_dir():
        raise SceneError(f"{text}: is a folder, not a scene file")
    if not path.exists():
        names = ", ".join(builtins) or "none found"
        raise SceneError(f"{text}: no such scene file (and not a built-in scene: {names})")
    return path.stem, path, False


_UNREFERENCED = re.compile(r'unreferenced propert(?:y|ies) in (\w+) plugin of type "([^"]+)": \w+ "([^"]+)"')


def _locate(message: str, root: ET.Element, lines: Lines | None) -> str | None:
    """``file:line`` of the parameter a Mitsuba 3 "unreferenced property" error names,
    when the user's file gave it (Mitsuba only sees the regenerated XML)."""
    m = _UNREFERENCED.search(message)
    if not m or not lines:
        return None
    tag, _, name = m.groups()
    for parent in root.iter(tag):
        for el in parent:
            if el.get("name") == name and el in lines:
                return f"{lines[el][0]}:{lines[el][1]}"
    return None


def load_scene(spec: "str | os.PathLike | None | mi.Scene | Mapping[str, Any]",
               resolution: tuple[int, int] | int | None = None,
               warn: bool = True) -> LoadedScene:
    """Load a scene for the renderer.

    ``spec``: None (the default built-in scene), a built-in name (see
    :func:`builtin_scenes`), a path to a Mitsuba 3 or Mitsuba 0.6 XML file, or what a
    Mitsuba 3 script has: a loaded ``mi.Scene`` or a scene dict for ``mi.load_dict``
    (see :func:`load_mitsuba`).
    ``resolution``: (W, H) overrides the film size; an int W keeps the film's aspect.
    ``warn``: print each import note as a warning line on stderr.
    Raises :class:`SceneError` (a usage error, one line) on any problem.
    """
    if isinstance(spec, Mapping) or type(spec).__name__ == "Scene":
        return load_mitsuba(spec, resolution=resolution)
    name, path, is_builtin = _resolve_spec(spec)
    label = name if is_builtin else os.fspath(spec)
    try:
        text = path.read_bytes()
    except OSError as exc:
        raise SceneError(f"{label}: cannot read: {exc.strerror or exc}") from None
    root, lines = parse_xml(text, label)
    return load_tree(root, name=name, path=path, label=label, resolution=resolution, lines=lines, warn=warn)


def load_tree(root: ET.Element, name: str, path: Path | None, label: str | None = None,
              resolution: tuple[int, int] | int | None = None, lines: Lines | None = None,
              warn: bool = False) -> LoadedScene:
    """Load an already-parsed scene tree (modified in place). ``path`` is the file it came
    from (relative references resolve against its folder), or None; ``lines`` maps
    elements to (file, line) for messages."""
    label = label or name
    if root.tag != "scene":
        raise SceneError(f"{label}: the root element is <{root.tag}>, not <scene>")
    version_text = root.get("version")
    version = parse_version(version_text, label)
    folder = path.resolve().parent if path is not None else None
    digest = hashlib.sha256(ET.tostring(root, encoding="utf-8"))
    _hash_included_files(root, folder, digest)
    notes: list[str] = []
    ctx = Context()
    try:
        if version[0] == 0:
            from . import mi06
            notes = mi06.translate(root, label=label, folder=folder, lines=lines, ctx=ctx)
        elif version[0] not in (2, 3):
            raise SceneError(f"{label}: scene version {version_text} is neither Mitsuba 0.x nor 3.x")
        refuse_unsupported(root, label, lines)  # both dialects; nothing the import produced may slip through
        max_depth, params = take_integrator(root)
        apply_resolution(root, resolution, label)
        if folder is not None:
            check_files(root, folder, label)
            _absolutise_files(root, folder)
        _hash_referenced_files(root, digest)

        ensure_variant()
        import mitsuba as mi

        xml = ET.tostring(root, encoding="unicode")
        try:
            with _ResolverScope(folder):
                scene = mi.load_string(xml)
        except Exception as exc:  # Mitsuba raises RuntimeError; anything else is the same to the user
            line = mitsuba_error_line(exc)
            raise SceneError(f"{_locate(line, root, lines) or label}: {line}") from None
    finally:
        ctx.cleanup()  # derived bitmaps are read at load time
    sensors = scene.sensors()
    if len(sensors) == 0:
        raise SceneError(f"{label}: the scene has no sensor")
    if warn:
        for note in notes:
            sys.stderr.write(f"ppmrecon: warning: scene import: {note}\n")
    size = sensors[0].film().size()
    return LoadedScene(scene=scene, name=name, path=path, width=int(size[0]), height=int(size[1]),
                       max_depth=max_depth, integrator_params=params,
                       source_version=version_text or "", notes=notes, content_hash=digest.hexdigest())


# --------------------------------------------------------------------------- Mitsuba 3 objects

#: Mitsuba 3 class names (``str(obj)`` up to ``[``) of the emitter and sensor types above.
EMITTER_CLASSES = {"AreaLight": "area", "PointLight": "point", "SpotLight": "spot",
                   "DirectionalEmitter": "directional", "EnvironmentMapEmitter": "envmap",
                   "ConstantBackgroundEmitter": "constant", "SunskyEmitter": "sunsky", "Projector": "projector"}
SENSOR_CLASSES = {"PerspectiveCamera": "perspective", "ThinLensCamera": "thinlens",
                  "OrthographicCamera": "orthographic"}
_INT_FIELD = r"\b{}\s*=\s*(-?\d+)"


def _class_name(obj: Any) -> str:
    # Mitsuba 3 objects print as "ClassName[...]"; their Python type is only the base class.
    return str(obj).split("[", 1)[0].strip()


def _dict_with_resolution(scene: Mapping[str, Any], resolution: tuple[int, int] | int | None,
                          label: str) -> dict[str, Any]:
    """A copy of a scene dict whose sensors' films have the size ``resolution`` (the
    user's dict is left as it was; only the copied levels are changed)."""
    out = dict(scene)
    if resolution is None:
        return out
    for key, value in scene.items():
        if not (isinstance(value, Mapping) and value.get("type") in SUPPORTED_SENSORS):
            continue
        film = dict(value.get("film") or {"type": "hdrfilm"})
        if isinstance(resolution, int):  # keep the film's aspect ratio (hdrfilm's default 768x576)
            w, h = int(film.get("width", 768)), int(film.get("height", 576))
            size = (resolution, max(1, round(resolution * h / w)))
        else:
            size = resolution
        film["width"], film["height"] = int(size[0]), int(size[1])
        film.pop("crop_width", None), film.pop("crop_height", None)
        film.pop("crop_offset_x", None), film.pop("crop_offset_y", None)
        out[key] = dict(value, film=film)
    return out


def check_mitsuba_scene(scene: "mi.Scene", label: str) -> None:
    """Refuse what the renderer does not simulate in a loaded ``mi.Scene``, as
    :func:`refuse_unsupported` does for files: media, other emitter and sensor types."""
    for shape in scene.shapes():
        if shape.interior_medium() is not None or shape.exterior_medium() is not None:
            raise SceneError(f"{label}: shape {_class_name(shape)} has an interior/exterior medium: "
                             "participating media are not simulated by the ppmrecon renderer")
    if not scene.emitters():
        raise SceneError(f"{label}: the scene has no emitter: there is nothing to trace photons from")
    for emitter in scene.emitters():
        if _class_name(emitter) not in EMITTER_CLASSES:
            raise SceneError(f"{label}: emitter {_class_name(emitter)} is not supported by the ppmrecon renderer "
                             f"(supported: {', '.join(SUPPORTED_EMITTERS)})")
    if not scene.sensors():
        raise SceneError(f"{label}: the scene has no sensor")
    sensor = scene.sensors()[0]
    if _class_name(sensor) not in SENSOR_CLASSES:
        raise SceneError(f"{label}: sensor {_class_name(sensor)} is not supported by the ppmrecon renderer "
                         f"(supported: {', '.join(SUPPORTED_SENSORS)})")


def load_mitsuba(scene: "mi.Scene | Mapping[str, Any]", resolution: tuple[int, int] | int | None = None,
                 name: str = "mitsuba_scene") -> LoadedScene:
    """Adapt what a Mitsuba 3 script builds: a loaded ``mi.Scene`` or a scene dict
    (``{"type": "scene", ...}``, loaded here with ``mi.load_dict``).

    The scene must be loaded under a variant the renderer runs (``llvm_ad_rgb`` or
    ``cuda_ad_rgb``); with a dict, one is activated if none is. ``resolution`` sets the
    film size of a dict; a loaded ``mi.Scene`` keeps its own (a film cannot be resized
    after loading). ``max_depth``/``rr_depth`` are read from the scene's integrator when
    it has one that states them (Mitsuba's ``path``, ``volpath``, ...), as for files.
    A scene given as an object has no file, so it has no content hash and its renders
    cannot be resumed from a state file.
    """
    from ..backend import VARIANTS

    if isinstance(scene, Mapping):
        if scene.get("type") != "scene":
            raise SceneError(f"{name}: a Mitsuba scene dict needs \"type\": \"scene\", got {scene.get('type')!r}")
        ensure_variant()
    elif resolution is not None:
        raise SceneError(f"{name}: resolution= applies to scene files and dicts; a loaded mi.Scene keeps its "
                         "film size (set the film's width/height before loading it)")
    import mitsuba as mi

    if mi.variant() not in VARIANTS:
        raise SceneError(f"{name}: Mitsuba variant {mi.variant()} is active; the ppmrecon renderer runs "
                         f"{' or '.join(VARIANTS)} (mi.set_variant before building the scene)")
    if isinstance(scene, Mapping):
        try:
            scene = mi.load_dict(_dict_with_resolution(scene, resolution, name))
        except Exception as exc:  # Mitsuba raises RuntimeError; anything else is the same to the user
            raise SceneError(f"{name}: {mitsuba_error_line(exc)}") from None
    elif not isinstance(scene, mi.Scene):
        raise SceneError(f"{name}: expected a mi.Scene of the active variant {mi.variant()}, "
                         f"got {type(scene).__module__}.{type(scene).__name__}")
    check_mitsuba_scene(scene, name)
    integrator = scene.integrator()
    text = "" if integrator is None else str(integrator)
    params: dict[str, Any] = {"type": _class_name(integrator)} if integrator is not None else {}
    max_depth = None
    if m := re.search(_INT_FIELD.format("max_depth"), text):
        max_depth = int(m.group(1))
    if m := re.search(_INT_FIELD.format("rr_depth"), text):
        params["rr_depth"] = int(m.group(1))
    size = scene.sensors()[0].film().size()
    return LoadedScene(scene=scene, name=name, path=None, width=int(size[0]), height=int(size[1]),
                       max_depth=max_depth, integrator_params=params)


def check_report(loaded: LoadedScene) -> str:
    """What ``ppmrecon-render SCENE --check`` prints: the loaded scene's size, its
    plugins by kind, and every import note (approximation), one a line."""
    scene = loaded.scene

    def kinds(objs: Any) -> str:
        names: dict[str, int] = {}
        for o in objs:
            key = str(o).split("[", 1)[0].strip() or type(o).__name__  # "SunskyEmitter[...]" -> its class
            names[key] = names.get(key, 0) + 1
        return ", ".join(f"{n} {k}" for k, n in sorted(names.items())) or "none"

    lines = [f"{loaded.label}: loaded (scene version {loaded.source_version or '?'}), "
             f"{loaded.width}x{loaded.height}, max_depth {loaded.max_depth if loaded.max_depth is not None else -1}",
             f"  shapes: {kinds(scene.shapes())}",
             f"  emitters: {kinds(scene.emitters())}",
             f"  import notes: {len(loaded.notes) if loaded.notes else 'none (nothing approximated)'}"]
    lines += [f"  - {n}" for n in loaded.notes]
    return "\n".join(lines) + "\n"
