"""Maps RenderVars to harmonizer inputs and finds their channels in a file.

The denoise stage's guides are roles too: ``albedo`` (linear reflectance,
Cycles' Denoising Albedo, Karma's and Arnold's albedo AOVs) and
``denoise_normal`` (the normal the renderer's denoiser would use, in any
space, such as Cycles' camera-space Denoising Normal; without it the denoiser
reads the ``normal`` var).

The inserted objects' ids are the role ``insert_id`` (integer ids held as
floats, 0 where a pixel is no inserted object; Hydra's ``primId`` and
``instanceId`` AOVs, an object id AOV): each id is then one object with its
own harmonization, even where objects touch. Without an ``insert_mask`` var
the mask is 1 where the id is above 0, so an id var that names every prim
(Hydra's ``primId``) wants the mask beside it.

A var's role comes from (first match): the user mapping (``--map VAR=ROLE``),
the var's ``harmonizer:role`` attribute, its ``sourceName``, its prim name.
Channels come from the var's ``harmonizer:channels`` attribute, else from the
AOV name (``driver:parameters:aov:name``), the prim name or ``sourceName``
with a component suffix (``.R .G .B .A``, ``.X .Y .Z .W``, lower case too),
else bare ``R G B A`` for color, ``Z`` for depth and ``A`` for coverage.
Channels are always looked up by name: OpenImageIO reorders EXR channels.
"""

from __future__ import annotations

from dataclasses import dataclass

from .errors import VarError
from .settings import ProductInfo, VarInfo

#: Roles (harmonizer inputs) and the components each needs.
ROLES: dict[str, int] = {
    "color": 3,
    "depth": 1,
    "motion": 2,
    "normal": 3,
    "coverage": 1,
    "insert_mask": 1,
    "insert_id": 1,
    "albedo": 3,
    "denoise_normal": 3,
}

_ALIASES: dict[str, set[str]] = {
    "color": {
        "color",
        "ci",
        "c",
        "beauty",
        "rgba",
        "rgb",
        "combined",
        "c.*",
        "lpe:c.*",
    },
    "depth": {"depth", "z", "pz", "cameradepth", "zdepth", "depth.z"},
    "motion": {
        "motion",
        "motionvector",
        "motionvectors",
        "mv",
        "vector",
        "motion_vector",
    },
    "normal": {"normal", "normals", "n", "nn"},
    "coverage": {"alpha", "a", "coverage"},
    "insert_mask": {
        "insert",
        "insertmask",
        "insert_mask",
        "mask.insert",
        "mask_insert",
    },
    "insert_id": {
        "insert_id",
        "insertid",
        "mask.id",
        "mask_id",
        "objectid",
        "object_id",
        "primid",
        "prim_id",
        "instanceid",
        "instance_id",
    },
    "albedo": {
        "albedo",
        "diffuse_albedo",
        "diffusealbedo",
        "denoise_albedo",
        "denoisealbedo",
        "denoising_albedo",
        "denoising albedo",
        "albedo_denoise",
    },
    "denoise_normal": {
        "denoise_normal",
        "denoisenormal",
        "denoising_normal",
        "denoising normal",
        "normal_denoise",
    },
}

_SUFFIXES: dict[int, list[tuple[str, ...]]] = {
    4: [
        ("R", "G", "B", "A"),
        ("r", "g", "b", "a"),
        ("X", "Y", "Z", "W"),
        ("x", "y", "z", "w"),
    ],
    3: [("R", "G", "B"), ("r", "g", "b"), ("X", "Y", "Z"), ("x", "y", "z")],
    2: [("X", "Y"), ("x", "y"), ("U", "V"), ("u", "v"), ("R", "G"), ("r", "g")],
    1: [
        ("",),
        ("Z",),
        ("z",),
        ("X",),
        ("x",),
        ("R",),
        ("r",),
        ("Y",),
        ("y",),
        ("V",),
        ("v",),
        ("A",),
        ("a",),
    ],
}


def parse_role(text: str, where: str) -> str:
    """Normalizes a role name (``insert-mask`` -> ``insert_mask``)."""
    r = (
        text.strip()
        .lower()
        .replace("-", "_")
        .replace("insertmask", "insert_mask")
        .replace("insertid", "insert_id")
    )
    if r == "mask":
        r = "insert_mask"
    if r not in ROLES and r != "ignore":
        raise VarError(
            f"{where}: unknown role {text!r} (expected one of {', '.join(ROLES)} or ignore)"
        )
    return r


def role_of(var: VarInfo, user_map: dict[str, str] | None = None) -> str | None:
    """The harmonizer input a var feeds, or None (kept, not used)."""
    if user_map:
        for key in (var.name, var.path):
            if key in user_map:
                r = parse_role(user_map[key], f"--map {key}")
                return None if r == "ignore" else r
    if var.role:
        r = parse_role(var.role, f"RenderVar {var.path} harmonizer:role")
        return None if r == "ignore" else r
    for key in (var.source_name, var.aov_name or "", var.name):
        k = key.strip().lower()
        if not k:
            continue
        for role, names in _ALIASES.items():
            if k in names:
                return role
    return None


@dataclass
class Binding:
    """A var bound to a role, with the channel names to read for it."""

    role: str
    var: VarInfo
    channels: list[str]
    #: Channel of the color var's alpha (coverage), when the file has one.
    alpha: str | None = None


def map_vars(
    product: ProductInfo, user_map: dict[str, str] | None = None
) -> dict[str, VarInfo]:
    """Role -> var for one product. Raises when two vars claim one role or when
    there is no color var."""
    out: dict[str, VarInfo] = {}
    for v in product.vars:
        r = role_of(v, user_map)
        if r is None:
            continue
        if r in out:
            raise VarError(
                f"render product {product.path}: RenderVars {out[r].path} and {v.path} both map to {r}; "
                f'set harmonizer:role = "ignore" on one or pass --map {v.name}=ignore'
            )
        out[r] = v
    if "color" not in out:
        names = ", ".join(
            f"{v.name} (sourceName {v.source_name!r})" for v in product.vars
        )
        raise VarError(
            f"render product {product.path}: no color RenderVar among orderedVars [{names}]; "
            'name one color/Ci/beauty, set harmonizer:role = "color" or pass --map VAR=color'
        )
    return out


def _bases(var: VarInfo) -> list[str]:
    seen: list[str] = []
    for b in (var.aov_name, var.name, var.source_name):
        if b and b not in seen:
            seen.append(b)
    return seen


def find_channels(role: str, var: VarInfo, names: list[str], where: str) -> Binding:
    """Finds the channels of ``var`` for ``role`` among the file's channel
    ``names``; ``where`` names the product, file and frame for errors."""
    need = ROLES[role]
    have = set(names)
    if var.channels:
        missing = [c for c in var.channels if c not in have]
        if missing or len(var.channels) < need:
            raise VarError(
                f"{where}: RenderVar {var.path} ({role}): harmonizer:channels {var.channels} "
                + (
                    f"not in the file (missing {missing}; "
                    if missing
                    else f"has fewer than {need} channels ("
                )
                + f"channels present: {sorted(have)})"
            )
        alpha = var.channels[3] if role == "color" and len(var.channels) > 3 else None
        return Binding(role, var, var.channels[:need], alpha)
    comps = max(var.components, need)
    tried: list[str] = []
    #: The first channel set found in part: (its channels, those present).
    partial: tuple[list[str], list[str]] | None = None
    for base in _bases(var):
        for n in sorted({comps, need}, reverse=True):
            for suf in _SUFFIXES.get(n, []):
                chans = [f"{base}.{s}" if s else base for s in suf]
                tried.append(",".join(chans))
                present = [c for c in chans[:need] if c in have]
                if present and len(present) < need and partial is None:
                    partial = (chans[:need], present)
                if len(present) == need:
                    alpha = None
                    if role == "color":
                        # The alpha beside the color, whatever the dataType says.
                        a = {"R": "A", "r": "a", "X": "W", "x": "w"}[suf[0]]
                        alpha = f"{base}.{a}" if f"{base}.{a}" in have else None
                    return Binding(role, var, chans[:need], alpha)
    bare = {"color": ("R", "G", "B"), "depth": ("Z",), "coverage": ("A",)}.get(role)
    if bare is not None:
        tried.append(",".join(bare))
        if all(c in have for c in bare):
            alpha = "A" if role == "color" and "A" in have else None
            return Binding(role, var, list(bare), alpha)
    if partial is not None:
        chans, present = partial
        missing = [c for c in chans if c not in present]
        raise VarError(
            f"{where}: RenderVar {var.path} ({role}): channel {missing[0]!r} is missing: {role} needs "
            f"{need} channels ({', '.join(chans)}) and the file has only {', '.join(present)} of them "
            f"(channels present: {sorted(have)}); write all {need}, or set harmonizer:channels on the var"
        )
    raise VarError(
        f"{where}: RenderVar {var.path} ({role}, dataType {var.data_type}): no matching channels "
        f"(tried {'; '.join(tried[:8])}{' ...' if len(tried) > 8 else ''}; channels present: {sorted(have)}); "
        "set harmonizer:channels on the var"
    )
