"""Mitsuba 0.6 BSDFs -> Mitsuba 3 BSDFs (0.6 documentation, section 8.2 "Surface
scattering models").

Same plugin, same parameters (after the renames of :mod:`.xml06`): ``diffuse``,
``dielectric``, ``thindielectric``, ``roughdielectric``, ``conductor``,
``roughconductor``, ``plastic``, ``roughplastic``, ``blendbsdf``, ``mask``,
``twosided``. Rewritten exactly: ``mixturebsdf`` (nested ``blendbsdf``), conductor
defaults and ``extEta``. Approximated, each noted: the ``as``/``phong`` microfacet
distributions, ``roughdiffuse``, ``phong``, ``ward``, ``coating``, ``roughcoating``,
``bumpmap``. Refused: ``difftrans`` (Mitsuba 3 has no diffuse transmitter), ``hk``,
``irawan``.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np

from .common import (Context, RuleList, child, const_rgb, ensure_variant, float_of, floats, fmt,
                     param_float, params, plugins, remove, replace, walk)
from .textures import _by_id, scaled

RULES = RuleList()

KNOWN = frozenset({"diffuse", "roughdiffuse", "dielectric", "thindielectric", "roughdielectric",
                   "conductor", "roughconductor", "plastic", "roughplastic", "coating", "roughcoating",
                   "bumpmap", "phong", "ward", "mixturebsdf", "blendbsdf", "mask", "twosided", "difftrans"})
#: Known to 0.6 but with no Mitsuba 3 counterpart nor a faithful approximation.
REFUSED = {"difftrans": "Mitsuba 3 has no diffuse transmission BSDF"}

_COLOR_TAGS = ("rgb", "float", "texture", "ref", "spectrum", "srgb")


def _bsdf(tag_type: str, **attrs: str) -> ET.Element:
    el = ET.Element("bsdf", {"type": tag_type, **attrs})
    el.tail = "\n"
    return el


def _take_over(old: ET.Element, new: ET.Element, parent: ET.Element, ctx: Context) -> None:
    """Put ``new`` where ``old`` was, with its id/name and its line for messages."""
    for key in ("id", "name"):
        if old.get(key) is not None:
            new.set(key, old.get(key))
    if old in ctx.lines:
        ctx.lines[new] = ctx.lines[old]
    replace(parent, old, new)


def _nested_bsdfs(el: ET.Element, ids: dict[str, ET.Element]) -> list[ET.Element]:
    """Nested BSDFs of ``el``, inline or ``<ref>`` to a BSDF, in order."""
    out = []
    for c in el:
        if c.tag == "bsdf":
            out.append(c)
        elif c.tag == "ref" and ids.get(c.get("id")) is not None and ids[c.get("id")].tag == "bsdf":
            out.append(c)
    return out


def blend(weight: float | ET.Element, a: ET.Element, b: ET.Element) -> ET.Element:
    """Mitsuba 3 ``blendbsdf``: (1 - weight) a + weight b."""
    el = _bsdf("blendbsdf")
    if isinstance(weight, ET.Element):
        weight.set("name", "weight")
        el.append(weight)
    else:
        child(el, "float", "weight", float(weight))
    a.attrib.pop("name", None)
    b.attrib.pop("name", None)
    el.extend([a, b])
    return el


def black() -> ET.Element:
    """A BSDF that absorbs everything (for mixtures that do not sum to one)."""
    el = _bsdf("diffuse")
    child(el, "rgb", "reflectance", [0.0, 0.0, 0.0])
    return el


def fresnel_dielectric(cos_i: np.ndarray, eta: float) -> np.ndarray:
    """Unpolarised Fresnel reflectance of a smooth dielectric (relative IOR ``eta``)."""
    cos_i = np.clip(cos_i, 0.0, 1.0)
    sin_t2 = (1.0 - cos_i ** 2) / eta ** 2
    cos_t = np.sqrt(np.clip(1.0 - sin_t2, 0.0, None))
    rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    return np.where(sin_t2 >= 1.0, 1.0, 0.5 * (rs ** 2 + rp ** 2))


def fresnel_diffuse_reflectance(eta: float, n: int = 4096) -> float:
    """Cosine-weighted hemispherical average of the Fresnel reflectance,
    2 int_0^1 F(mu) mu dmu (midpoint rule): the fraction of diffuse light a smooth
    coating of relative IOR ``eta`` reflects."""
    mu = (np.arange(n) + 0.5) / n
    return float(2.0 * np.mean(fresnel_dielectric(mu, eta) * mu))


def phong_alpha(exponent: float) -> float:
    """Beckmann roughness whose lobe matches 0.6's Phong lobe cos^n(angle to the mirror
    direction): near the peak cos^n(2 theta_h) ~ exp(-2 n theta_h^2) and Beckmann is
    ~ exp(-theta_h^2 / alpha^2), so alpha = 1 / sqrt(2n); the Walter et al. (2007)
    Phong-to-Beckmann form sqrt(2 / (n' + 2)) with the half-vector exponent n' = 4n,
    i.e. 1 / sqrt(2n + 1), keeps alpha finite at n = 0."""
    return 1.0 / math.sqrt(2.0 * exponent + 1.0)


def _mean(rgb: list[float]) -> float:
    return sum(rgb) / len(rgb)


def _diffuse_plus_lobe(el: ET.Element, parent: ET.Element, lobe: ET.Element, ctx: Context,
                       ids: dict[str, ET.Element], what: str) -> None:
    """Replace a 0.6 ``phong``/``ward`` (kd/pi + ks x lobe, no Fresnel) by
    blendbsdf(w, diffuse(kd / (1 - w)), lobe(ks / w)) with w = mean(ks) / mean(kd + ks),
    which is exact in energy and keeps both reflectances <= 1 when kd + ks <= 1; with a
    textured reflectance w = 1/2 and both are doubled (textures baked)."""
    p = params(el)
    kd_node, ks_node = p.get("diffuse_reflectance"), p.get("specular_reflectance")
    kd, ks = const_rgb(kd_node, 0.5), const_rgb(ks_node, 0.2)
    if kd is not None and ks is not None:
        total = _mean(kd) + _mean(ks)
        w = _mean(ks) / total if total > 0 else 0.0
        kd_new = ET.Element("rgb", {"value": fmt([v / (1 - w) for v in kd] if w < 1 else kd)})
        ks_new = ET.Element("rgb", {"value": fmt([v / w for v in ks] if w > 0 else ks)})
    else:
        w = 0.5
        kd_new = scaled(kd_node if kd_node is not None else ET.Element("rgb", {"value": "0.5"}), 2.0, ctx, ids)
        ks_new = scaled(ks_node if ks_node is not None else ET.Element("rgb", {"value": "0.2"}), 2.0, ctx, ids)
    diffuse = _bsdf("diffuse")
    kd_new.set("name", "reflectance")
    diffuse.append(kd_new)
    ks_new.set("name", "specular_reflectance")
    lobe.append(ks_new)
    new = diffuse if w == 0 else lobe if w == 1 else blend(w, diffuse, lobe)
    _take_over(el, new, parent, ctx)
    ctx.note(f"approximated by {what}, blend weight {w:.3g}", el)


@RULES.rule("microfacet_distribution")
def microfacet_distribution(root: ET.Element, ctx: Context) -> None:
    """``<string name="distribution" value="as">`` (Ashikhmin-Shirley) and ``"phong"`` on
    rough BSDFs -> ``"beckmann"`` with the same alpha(s), noted. 0.6 turned alpha into the
    Phong/AS exponent e = 2/alpha^2 - 2, which is Walter et al.'s (2007) match of the
    Beckmann lobe of width alpha (AS is the anisotropic Phong form); GGX with the same
    alpha would have much longer tails. ``beckmann``/``ggx`` are kept (0.6 doc section 8.2, roughconductor)."""
    for el, parent in walk(root):
        if el.tag == "string" and el.get("name") == "distribution" and parent is not None \
                and parent.tag == "bsdf":
            value = (el.get("value") or "").strip().lower()
            if value in ("as", "phong"):
                el.set("value", "beckmann")
                ctx.note(f"microfacet distribution '{value}' mapped to 'beckmann' (same alpha)", parent)
            elif value not in ("beckmann", "ggx"):
                ctx.refuse(el, f"has an unknown microfacet distribution '{value}'")


@RULES.rule("conductor_default_material")
def conductor_default_material(root: ET.Element, ctx: Context) -> None:
    """A 0.6 ``conductor``/``roughconductor`` with neither ``material`` nor ``eta``/``k``
    -> ``<string name="material" value="Cu">``: 0.6's default material was copper,
    Mitsuba 3's is ``none`` (a perfect mirror). Named materials (0.6 doc section 8.2, conductor)
    are the same list in Mitsuba 3; an unknown name is refused by Mitsuba 3 by name."""
    for el, _ in plugins(root, "bsdf", ("conductor", "roughconductor")):
        p = params(el)
        if "material" not in p and "eta" not in p and "k" not in p:
            child(el, "string", "material", "Cu", index=0)


@RULES.rule("conductor_ext_eta")
def conductor_ext_eta(root: ET.Element, ctx: Context) -> None:
    """``extEta`` (the exterior IOR, a number or a name like "air") on 0.6
    ``conductor``/``roughconductor`` -> folded into Mitsuba 3's relative ``eta``/``k``:
    dropped when it is 1 within 1e-3 (vacuum, air: < 0.03 % change) or the material is
    ``none``; otherwise eta and k (explicit, or those of the named material as Mitsuba 3
    tabulates them in RGB) are divided by it and written as ``<rgb name="eta|k">``."""
    for el, _ in plugins(root, "bsdf", ("conductor", "roughconductor")):
        p = params(el)
        ext_el = p.get("extEta", p.get("ext_eta"))
        if ext_el is None:
            continue
        ext = float_of(ext_el, ctx)
        el.remove(ext_el)
        mat_el = p.get("material")
        material = (mat_el.get("value") if mat_el is not None else "none") or "none"
        if abs(ext - 1.0) <= 1e-3 or ("eta" not in p and material.lower() == "none"):
            continue
        if ext <= 0:
            ctx.refuse(ext_el, "must be positive")
        if "eta" in p or "k" in p:
            for key in ("eta", "k"):
                if key not in p:
                    continue
                node = p[key]
                if node.tag not in ("rgb", "float"):
                    ctx.refuse(node, "must be a float or rgb value to fold extEta into it")
                node.set("value", fmt([v / ext for v in floats(node.get("value", ""))]))
            continue
        ensure_variant()
        import mitsuba as mi
        try:
            cond = mi.load_dict({"type": "conductor", "material": material})
        except Exception:
            ctx.refuse(mat_el if mat_el is not None else el, f"names an unknown conductor material '{material}'")
        tp = mi.traverse(cond)
        for key in ("eta", "k"):
            rgb = [float(v) / ext for v in np.asarray(tp[f"{key}.value"], dtype=np.float64).ravel()]
            child(el, "rgb", key, rgb * 3 if len(rgb) == 1 else rgb)
        if mat_el is not None:
            el.remove(mat_el)
        ctx.note(f"conductor '{material}' in a medium of IOR {ext:g}: eta, k divided by it (RGB)", el)


@RULES.rule("roughdiffuse")
def roughdiffuse(root: ET.Element, ctx: Context) -> None:
    """0.6 ``roughdiffuse`` (Oren-Nayar, ``alpha`` default 0.2, ``useFastApprox``) ->
    Mitsuba 3 ``diffuse`` with the same ``reflectance``, noted: Mitsuba 3 has no
    Oren-Nayar model; the albedo is kept, the retro-reflective flattening is lost."""
    for el, _ in plugins(root, "bsdf", ("roughdiffuse",)):
        alpha = params(el).get("alpha")
        a = alpha.get("value") if alpha is not None and alpha.tag == "float" else "0.2" if alpha is None else "textured"
        ctx.note(f"Oren-Nayar roughness (alpha {a}) dropped: Lambertian 'diffuse'", el)
        remove(el, "alpha", "useFastApprox")
        el.set("type", "diffuse")


@RULES.rule("phong")
def phong(root: ET.Element, ctx: Context) -> None:
    """0.6 ``phong`` (modified Phong: kd/pi + ks (n+2)/(2 pi) cos^n of the angle to the
    mirror direction; ``exponent`` 30, ``specularReflectance`` 0.2,
    ``diffuseReflectance`` 0.5) -> ``blendbsdf`` of ``diffuse`` and a ``roughconductor``
    (``material="none"``, Beckmann, alpha = 1/sqrt(2n + 1), the lobe of matching width;
    see :func:`phong_alpha`), weights as in :func:`_diffuse_plus_lobe`; noted. A
    textured exponent is refused."""
    ids = _by_id(root)
    for el, parent in plugins(root, "bsdf", ("phong",)):
        node = params(el).get("exponent")
        if node is not None and node.tag not in ("float", "integer"):
            ctx.refuse(node, "(a textured Phong exponent) is not supported by the import layer")
        n = float_of(node, ctx) if node is not None else 30.0
        if n < 0:
            ctx.refuse(node, f"must be non-negative, got {n:g}")
        lobe = _bsdf("roughconductor")
        child(lobe, "string", "material", "none")
        child(lobe, "string", "distribution", "beckmann")
        child(lobe, "float", "alpha", phong_alpha(n))
        _diffuse_plus_lobe(el, parent, lobe, ctx, ids,
                           f"diffuse + Beckmann mirror lobe alpha {phong_alpha(n):.3g} (exponent {n:g})")


@RULES.rule("ward")
def ward(root: ET.Element, ctx: Context) -> None:
    """0.6 ``ward`` (anisotropic Ward; ``variant`` ward/ward-duer/balanced,
    ``alphaU``/``alphaV`` 0.1, ``specularReflectance`` 0.2, ``diffuseReflectance`` 0.5)
    -> ``blendbsdf`` of ``diffuse`` and a ``roughconductor`` (``material="none"``,
    anisotropic Beckmann with alpha_u, alpha_v = alphaU, alphaV: Ward's exponent
    exp(-tan^2 theta_h (cos^2 phi / a_u^2 + sin^2 phi / a_v^2)) is Beckmann's), weights
    as in :func:`_diffuse_plus_lobe`; noted. Textured alphas are refused."""
    ids = _by_id(root)
    for el, parent in plugins(root, "bsdf", ("ward",)):
        p = params(el)
        alphas = []
        for key in ("alpha_u", "alpha_v"):
            node = p.get(key)
            if node is not None and node.tag not in ("float", "integer"):
                ctx.refuse(node, "(a textured Ward roughness) is not supported by the import layer")
            alphas.append(float_of(node, ctx) if node is not None else 0.1)
        lobe = _bsdf("roughconductor")
        child(lobe, "string", "material", "none")
        child(lobe, "string", "distribution", "beckmann")
        child(lobe, "float", "alpha_u", alphas[0])
        child(lobe, "float", "alpha_v", alphas[1])
        variant = p.get("variant")
        _diffuse_plus_lobe(el, parent, lobe, ctx, ids,
                           f"diffuse + anisotropic Beckmann mirror lobe alpha {alphas[0]:g}/{alphas[1]:g} "
                           f"(variant {variant.get('value') if variant is not None else 'balanced'})")


def _attenuation(el: ET.Element, ctx: Context) -> float:
    """exp(-2 sigmaA thickness): the coat's absorption at normal incidence, in and out."""
    p = params(el)
    sigma = p.get("sigmaA")
    if sigma is not None and sigma.tag not in ("rgb", "float"):
        ctx.refuse(sigma, "(a textured coating absorption) is not supported by the import layer")
    s = _mean(const_rgb(sigma, 0.0))
    return math.exp(-2.0 * s * param_float(el, "thickness", 1.0, ctx))


@RULES.rule("coating")
def coating(root: ET.Element, ctx: Context) -> None:
    """0.6 ``coating``/``roughcoating`` (a dielectric layer, ``intIOR`` bk7 over
    ``extIOR`` air, with absorption ``sigmaA`` over ``thickness``, on a nested BSDF;
    rough: ``distribution``, ``alpha``) -> over a ``diffuse`` base: Mitsuba 3
    ``plastic``/``roughplastic`` (the same coated-diffuse model) with the base's
    reflectance times exp(-2 sigmaA thickness); over any other base: ``blendbsdf``
    (w = F_dr, the coat's cosine-weighted Fresnel reflectance) of the base (absorption
    folded in by a blend with black) and a mirror (``conductor`` ``none``; rough:
    ``roughconductor`` with the coat's alpha) carrying ``specularReflectance``. Noted."""
    ids = _by_id(root)
    for el, parent in list(plugins(root, "bsdf", ("coating", "roughcoating"))):
        rough = el.get("type") == "roughcoating"
        p = params(el)
        nested = _nested_bsdfs(el, ids)
        if len(nested) != 1:
            ctx.refuse(el, f"needs exactly one nested BSDF, has {len(nested)}")
        base = nested[0]
        base_el = ids[base.get("id")] if base.tag == "ref" else base
        att = _attenuation(el, ctx)
        int_ior, ext_ior = p.get("int_ior"), p.get("ext_ior")
        eta = (float_of(int_ior, ctx) if int_ior is not None else 1.5046) / \
            (float_of(ext_ior, ctx) if ext_ior is not None else 1.000277)
        keep = [c for c in (int_ior, ext_ior, p.get("specular_reflectance")) if c is not None]
        if rough:
            keep += [c for c in (p.get("distribution"), p.get("alpha")) if c is not None]
        if base_el.get("type") == "diffuse":
            new = _bsdf("roughplastic" if rough else "plastic")
            for c in keep:
                new.append(c)
            refl = params(base_el).get("reflectance")
            if att != 1.0 or refl is None:
                refl = scaled(refl if refl is not None else ET.Element("rgb", {"value": "0.5"}), att, ctx, ids)
            else:
                refl = scaled(refl, 1.0, ctx, ids)
            refl.set("name", "diffuse_reflectance")
            new.append(refl)
            _take_over(el, new, parent, ctx)
            ctx.note(f"coated diffuse -> Mitsuba 3 '{new.get('type')}' (absorption x{att:.3g})", el)
            continue
        mirror = _bsdf("roughconductor" if rough else "conductor")
        child(mirror, "string", "material", "none")
        if rough:
            for key in ("distribution", "alpha"):
                if key in p:
                    mirror.append(p[key])
        if "specular_reflectance" in p:
            mirror.append(p["specular_reflectance"])
        el.remove(base)
        inner = base if att == 1.0 else blend(1.0 - att, base, black())
        w = fresnel_diffuse_reflectance(eta)
        new = blend(w, inner, mirror)
        _take_over(el, new, parent, ctx)
        ctx.note(f"coating over '{base_el.get('type')}' -> blend of base and mirror, weight F_dr={w:.3g}"
                 f" (eta {eta:.3g}), absorption x{att:.3g}", el)


@RULES.rule("bumpmap")
def bumpmap(root: ET.Element, ctx: Context) -> None:
    """0.6 ``bumpmap`` (a displacement texture, usually ``<texture type="scale">`` around
    a ``bitmap``, and a nested BSDF) -> Mitsuba 3 ``bumpmap`` with the inner texture and
    Mitsuba 3's ``scale`` set to the 0.6 scale factor; both perturb the shading normal by
    the texture gradient in uv. Noted (Mitsuba 3 differentiates the bilinear texture, 0.6
    used finite differences)."""
    for el, _ in plugins(root, "bsdf", ("bumpmap",)):
        texs = [c for c in el if c.tag == "texture" or (c.tag == "ref" and c.get("name") not in (None, "bsdf"))]
        if len(texs) != 1:
            ctx.refuse(el, f"needs exactly one displacement texture, has {len(texs)}")
        tex, factor = texs[0], 1.0
        while tex.tag == "texture" and tex.get("type") == "scale":
            factor *= param_float(tex, "scale", 1.0, ctx)
            inner = [c for c in tex if c.tag in ("texture", "ref")]
            if len(inner) != 1:
                ctx.refuse(tex, "needs exactly one nested texture")
            tex = inner[0]
        if tex is not texs[0]:
            replace(el, texs[0], tex)
        tex.set("name", "texture")
        remove(el, "scale")
        child(el, "float", "scale", factor)
        ctx.note(f"bump map scale {factor:g} (Mitsuba 3 differentiates the texture analytically)", el)


@RULES.rule("mixturebsdf")
def mixturebsdf(root: ET.Element, ctx: Context) -> None:
    """0.6 ``mixturebsdf`` (``weights="w1, w2, ..."``, one nested BSDF each, sum <= 1)
    -> nested Mitsuba 3 ``blendbsdf``: f = w1 f1 + (1 - w1) [w2/(1 - w1) f2 + ...], with a
    black BSDF taking 1 - sum(w) when the weights sum to less than one. Exact."""
    ids = _by_id(root)
    for el, parent in list(plugins(root, "bsdf", ("mixturebsdf",))):
        node = params(el).get("weights")
        if node is None:
            ctx.refuse(el, "has no weights")
        try:
            weights = floats(node.get("value", ""))
        except ValueError:
            ctx.refuse(node, f"has unreadable weights '{node.get('value')}'")
        nested = _nested_bsdfs(el, ids)
        if len(weights) != len(nested) or not nested:
            ctx.refuse(el, f"has {len(weights)} weights for {len(nested)} nested BSDFs")
        if any(w < 0 for w in weights) or sum(weights) > 1 + 1e-6:
            ctx.refuse(node, "must be non-negative and sum to at most 1")
        parts = list(zip(weights, nested))
        rest = 1.0 - sum(weights)
        if rest > 1e-6:
            parts.append((rest, black()))
        # Fold from the back: acc is the normalised mixture of parts[i:].
        acc_w, acc = parts[-1]
        for w, b in reversed(parts[:-1]):
            total = w + acc_w
            acc = blend(acc_w / total if total > 0 else 0.0, b, acc)
            acc_w = total
        _take_over(el, acc, parent, ctx)

