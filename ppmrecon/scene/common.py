"""Shared machinery of scene loading: the one-line error, element descriptions with the
line they came from, the rule registry of the Mitsuba 0.6 import, and small XML helpers.

Nothing here imports the rest of the package, so every plugin module (``spectra``,
``textures``, ``bsdfs``, ``emitters``, ``shapes``, ``sensors``, ``xml06``) and the loader
can import it without cycles.
"""

from __future__ import annotations

import atexit
import inspect
import math
import re
import shutil
import sys
import tempfile
import xml.etree.ElementTree as ET
import xml.parsers.expat
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, NoReturn

from ..errors import UsageError


class SceneError(UsageError):
    """A scene that cannot be loaded or is not supported; the message is one line."""


# --------------------------------------------------------------------------- messages

def one_line(text: str) -> str:
    """Collapse a (possibly multi-line) message into one line (list bullets become "; ")."""
    out = ""
    for part in str(text).splitlines():
        part = part.strip()
        if not part:
            continue
        if part.startswith("- "):
            out += ("; " if out and not out.endswith(":") else " ") + part[2:]
        else:
            out += (" " if out else "") + part
    return out


def mitsuba_error_line(exc: BaseException) -> str:
    """The essential line of a Mitsuba exception: no ``[file.cpp:123]`` tags, no
    positions in the regenerated XML string (they would not match the user's file)."""
    msg = str(exc).strip() or type(exc).__name__
    msg = re.sub(r"\[[\w.]+\.(?:cpp|h|hpp|py):\d+\]\s*", "", msg)
    msg = re.sub(r"(?:Error while loading|While loading|At) string \(line \d+, col \d+\):\s*", "", msg,
                 flags=re.IGNORECASE)
    msg = re.sub(r"\[(\w+)\]\s+", r"\1: ", msg)  # "[OBJMesh] Error ..." -> "OBJMesh: Error ..."
    return one_line(msg)


def describe(el: ET.Element) -> str:
    """``<tag type="..." id="..." name="...">`` for messages."""
    attrs = "".join(f' {k}="{el.get(k)}"' for k in ("type", "name", "id") if el.get(k) is not None)
    return f"<{el.tag}{attrs}>"


def ensure_variant() -> None:
    """Activate a Mitsuba variant unless one is already active (ours or the caller's)."""
    from ..backend import active_variant, choose_variant
    if active_variant() is not None:
        return
    mi = sys.modules.get("mitsuba")
    if mi is not None:
        try:
            if mi.variant() is not None:
                return
        except Exception:  # pragma: no cover - a broken import: let choose_variant say why
            pass
    choose_variant()


# --------------------------------------------------------------------------- parsing with lines

#: element -> (file label, line) of every element parsed from a user's file.
Lines = dict


def parse_xml(data: bytes | str, label: str) -> tuple[ET.Element, Lines]:
    """Parse XML into an ElementTree, remembering the line of every element (expat's
    position at the start tag), so refusals can say ``file.xml:12``."""
    builder = ET.TreeBuilder()
    lines: Lines = {}
    parser = xml.parsers.expat.ParserCreate()

    def start(tag: str, attrs: dict[str, str]) -> None:
        lines[builder.start(tag, attrs)] = (label, parser.CurrentLineNumber)

    parser.StartElementHandler = start
    parser.EndElementHandler = builder.end
    parser.CharacterDataHandler = builder.data
    try:
        parser.Parse(data, True)
        return builder.close(), lines
    except xml.parsers.expat.ExpatError as exc:
        raise SceneError(f"{label}: not valid XML: {one_line(str(exc))}") from None


# --------------------------------------------------------------------------- rules

@dataclass
class Context:
    """State shared by the rules while translating one file: where elements came from,
    the notes (approximations), and a scratch folder for bitmaps the import derives
    (a channel, a gamma, a scale, a rasterised grid) that Mitsuba 3 reads at load."""

    label: str = "<string>"
    folder: Path | None = None
    notes: list[str] = field(default_factory=list)
    lines: Lines = field(default_factory=dict)
    scratch: Path | None = None

    def where(self, el: ET.Element) -> str:
        """``file:line`` of an element (the label alone for generated elements)."""
        if el in self.lines:
            name, line = self.lines[el]
            return f"{name}:{line}"
        return self.label

    def refuse(self, el: ET.Element, why: str) -> NoReturn:
        raise SceneError(f"{self.where(el)}: Mitsuba 0.6 element {describe(el)} {why}")

    def note(self, text: str, el: ET.Element | None = None) -> None:
        """Record an approximation (once); with ``el``, prefixed by its file:line and tag."""
        if el is not None:
            text = f"{self.where(el)}: {describe(el)}: {text}"
        if text not in self.notes:
            self.notes.append(text)

    def scratch_file(self, stem: str, suffix: str = ".exr") -> Path:
        """A fresh path in this translation's scratch folder (removed after loading)."""
        if self.scratch is None:
            self.scratch = Path(tempfile.mkdtemp(prefix="ppmrecon-scene-"))
            atexit.register(shutil.rmtree, self.scratch, True)
        n = sum(1 for _ in self.scratch.iterdir())
        return self.scratch / f"{stem}-{n}{suffix}"

    def cleanup(self) -> None:
        if self.scratch is not None:
            shutil.rmtree(self.scratch, ignore_errors=True)
            self.scratch = None


@dataclass(frozen=True)
class Rule:
    """One rewrite of the import table: ``apply(root, ctx)`` edits the tree in place."""

    name: str
    apply: Callable[[ET.Element, Context], None]

    @property
    def doc(self) -> str:
        return inspect.getdoc(self.apply) or ""


RuleFn = Callable[[ET.Element, Context], None]


class RuleList(list):
    """The rules of one plugin module, in order; ``@rules.rule("name")`` appends one."""

    def rule(self, name: str) -> Callable[[RuleFn], RuleFn]:
        def deco(fn: RuleFn) -> RuleFn:
            if not inspect.getdoc(fn):
                raise TypeError(f"rule {name} needs a docstring")
            self.append(Rule(name, fn))
            return fn
        return deco


# --------------------------------------------------------------------------- tree helpers

def walk(root: ET.Element) -> Iterator[tuple[ET.Element, ET.Element | None]]:
    """(element, parent) pairs, depth first, skipping integrator subtrees (left to the
    loader). The list is taken before yielding, so rules may replace what they visit."""
    out: list[tuple[ET.Element, ET.Element | None]] = []
    stack: list[tuple[ET.Element, ET.Element | None]] = [(root, None)]
    while stack:
        el, parent = stack.pop()
        if el.tag == "integrator":
            continue
        out.append((el, parent))
        stack.extend((c, el) for c in reversed(list(el)))
    return iter(out)


def plugins(root: ET.Element, tag: str, types: tuple[str, ...] | None = None
            ) -> Iterator[tuple[ET.Element, ET.Element | None]]:
    """(element, parent) of every ``<tag type=...>`` with a type in ``types`` (any: None)."""
    for el, parent in walk(root):
        if el.tag == tag and (types is None or el.get("type") in types):
            yield el, parent


def params(el: ET.Element) -> dict[str, ET.Element]:
    """Direct child elements by their ``name`` attribute."""
    return {c.get("name"): c for c in el if c.get("name") is not None}


def floats(text: str) -> list[float]:
    return [float(t) for t in re.split(r"[,\s]+", text.strip()) if t]


def fmt(values: list[float] | tuple[float, ...]) -> str:
    return ", ".join(f"{v:.6g}" for v in values)


def replace(parent: ET.Element, old: ET.Element, new: ET.Element) -> None:
    new.tail = old.tail
    parent[list(parent).index(old)] = new


def child(parent: ET.Element, tag: str, name: str | None = None, value: object = None,
          index: int | None = None, **attrs: str) -> ET.Element:
    """Add ``<tag name=... value=...>`` to ``parent`` (at ``index``, else at the end)."""
    a = dict(attrs)
    if name is not None:
        a["name"] = name
    if value is not None:
        a["value"] = value if isinstance(value, str) else (fmt(value) if isinstance(value, (list, tuple))
                                                           else f"{value:.10g}" if isinstance(value, float)
                                                           else str(value))
    el = ET.Element(tag, a)
    el.tail = "\n"
    if index is None:
        parent.append(el)
    else:
        parent.insert(index, el)
    return el


def remove(parent: ET.Element, *names: str) -> None:
    """Remove the direct children named ``names`` (absent ones are fine)."""
    for c in list(parent):
        if c.get("name") in names:
            parent.remove(c)


#: 0.6's named indices of refraction (the same table Mitsuba 3 uses for int_ior/ext_ior).
IOR_TABLE: dict[str, float] = {
    "vacuum": 1.0, "helium": 1.000036, "hydrogen": 1.000132, "air": 1.000277,
    "carbon dioxide": 1.00045, "water": 1.3330, "acetone": 1.36, "ethanol": 1.361,
    "carbon tetrachloride": 1.461, "glycerol": 1.4729, "benzene": 1.501, "silicone oil": 1.52045,
    "bromine": 1.661, "water ice": 1.31, "fused quartz": 1.458, "pyrex": 1.470,
    "acrylic glass": 1.49, "polypropylene": 1.49, "bk7": 1.5046, "sodium chloride": 1.544,
    "amber": 1.55, "pet": 1.575, "diamond": 2.419,
}


def float_of(el: ET.Element, ctx: Context) -> float:
    """A float from a float/integer/string property (string: a named IOR or a number)."""
    value = (el.get("value") or "").strip()
    if el.tag == "string" and value.lower() in IOR_TABLE:
        return IOR_TABLE[value.lower()]
    try:
        return float(value)
    except ValueError:
        ctx.refuse(el, f"has value '{value}', which is neither a number nor a known IOR name")


def param_float(el: ET.Element, name: str, default: float, ctx: Context) -> float:
    """The float parameter ``name`` of a plugin element, or ``default``."""
    p = params(el).get(name)
    return default if p is None else float_of(p, ctx)


def const_rgb(node: ET.Element | None, default: float | None = None) -> list[float] | None:
    """The constant RGB of a colour parameter (``<rgb>`` or ``<float>``; spectra are
    already ``<rgb>`` when the BSDF rules run), ``default`` grey when absent, None when
    it is a texture or reference."""
    if node is None:
        return None if default is None else [default] * 3
    if node.tag in ("rgb", "float"):
        vals = floats(node.get("value", ""))
        return vals * 3 if len(vals) == 1 else vals
    return None


def srgb_to_linear(c: float) -> float:
    """sRGB transfer function inverse (IEC 61966-2-1), extended to c > 1 and c < 0."""
    s = math.copysign(1.0, c)
    c = abs(c)
    return s * (c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4)
