"""Real assets for the data generator: Sweet Home 3D furniture, photo textures
from ``nexuiz-textures`` and Blender's HDRIs.

``python -m training.synth.assets`` (any Python 3.9+, no bpy needed) makes sure
the Debian package ``sweethome3d-furniture`` is installed (``apt-get`` when run as
root), extracts each ``.sh3f`` library into ``training/assets/sh3d/<library>/``,
downloads ``nexuiz-textures`` (``apt-get download``, no root needed; skipped
with a note when it cannot be fetched) and extracts its floor, wall, metal,
stone and wood textures into ``training/assets/textures/nexuiz/``, writes
``training/assets/catalog.json`` (one entry per model: OBJ path, size in
metres, elevation, rotation, library, creator, license; one per texture) and
regenerates ``training/ATTRIBUTION.md``. Every step is idempotent: finished
work is skipped.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

TRAINING_DIR = Path(__file__).resolve().parent.parent
ASSETS_DIR = TRAINING_DIR / "assets"
SH3D_SYSTEM_DIR = Path("/usr/share/sweethome3d/furniture")
DEBIAN_PACKAGE = "sweethome3d-furniture"
CATALOG_VERSION = 2
#: Photo textures for floors and walls: a source the out-of-domain set does
#: not use (it takes extremetuxracer-data and openarena-081-textures).
TEXTURE_PACKAGE = "nexuiz-textures"
TEXTURE_LICENSE = "GPL-2+"
TEXTURE_COPYRIGHT = "the Nexuiz team and texture authors (the package's copyright file)"
_TEXTURE_WORDS = (
    "floor",
    "wall",
    "tile",
    "brick",
    "concrete",
    "wood",
    "stone",
    "rock",
    "metal",
    "plate",
    "ground",
    "dirt",
)
# Normal, gloss, glow and other maps, effects, trims and signs.
_TEXTURE_SKIP = ("_norm", "_gloss", "_glow", "_bump", "_shirt", "_pants", "_reflect", "_luma", "_alpha")
_TEXTURE_SKIP += ("sfx", "_fx", "light", "trim", "decal", "sky", "water", "logo", "sign", "font", "_d.", "_e.")


class AssetError(RuntimeError):
    """An asset could not be installed, extracted or parsed."""


def parse_properties(text: str) -> dict[str, str]:
    """Parses a Java ``.properties`` file (comments, continuations, ``\\u`` escapes of four hex digits)."""
    props: dict[str, str] = {}
    logical: list[str] = []
    pending = ""
    for raw in text.splitlines():
        line = raw.lstrip()
        if not pending and (not line or line[0] in "#!"):
            continue
        # An odd number of trailing backslashes continues the line.
        stripped = line.rstrip("\r")
        n = len(stripped) - len(stripped.rstrip("\\"))
        if n % 2 == 1:
            pending += stripped[:-1]
            continue
        logical.append(pending + stripped)
        pending = ""
    if pending:
        logical.append(pending)
    for line in logical:
        key_end = len(line)
        i = 0
        while i < len(line):
            c = line[i]
            if c == "\\":
                i += 2
                continue
            if c in "=: \t":
                key_end = i
                break
            i += 1
        key = line[:key_end]
        rest = line[key_end:].lstrip(" \t")
        if rest[:1] in ("=", ":"):
            rest = rest[1:].lstrip(" \t")
        props[_unescape(key)] = _unescape(rest)
    return props


def _unescape(s: str) -> str:
    out = []
    i = 0
    while i < len(s):
        c = s[i]
        if c == "\\" and i + 1 < len(s):
            n = s[i + 1]
            if n == "u" and i + 6 <= len(s):
                try:
                    out.append(chr(int(s[i + 2 : i + 6], 16)))
                    i += 6
                    continue
                except ValueError:
                    pass
            out.append({"t": "\t", "n": "\n", "r": "\r", "f": "\f"}.get(n, n))
            i += 2
            continue
        out.append(c)
        i += 1
    return "".join(out)


def ensure_package(system_dir: Path = SH3D_SYSTEM_DIR) -> list[Path]:
    """Installs ``sweethome3d-furniture`` with apt-get when missing; returns the libraries."""
    libs = sorted(system_dir.glob("*.sh3f")) if system_dir.is_dir() else []
    if libs:
        return libs
    if os.geteuid() != 0 or shutil.which("apt-get") is None:
        raise AssetError(
            f"no .sh3f libraries in {system_dir}; install the Debian package "
            f"'{DEBIAN_PACKAGE}' (apt-get install -y {DEBIAN_PACKAGE}) as root"
        )
    print(f"assets: installing {DEBIAN_PACKAGE} with apt-get", flush=True)
    for cmd in (["apt-get", "update"], ["apt-get", "install", "-y", DEBIAN_PACKAGE]):
        r = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        if r.returncode != 0:
            raise AssetError(f"'{' '.join(cmd)}' failed with exit {r.returncode}: {r.stdout[-2000:]}")
    libs = sorted(system_dir.glob("*.sh3f"))
    if not libs:
        raise AssetError(f"{DEBIAN_PACKAGE} installed but {system_dir} holds no .sh3f file")
    return libs


def _float(props: dict[str, str], key: str, default: float | None = None) -> float | None:
    v = props.get(key)
    if v is None or v.strip() == "":
        return default
    try:
        return float(v)
    except ValueError as e:
        raise AssetError(f"property '{key}' is not a number: {v!r}") from e


def extract_library(sh3f: Path, assets_dir: Path = ASSETS_DIR) -> dict:
    """Extracts one ``.sh3f`` library (once) and returns its catalog entry."""
    lib_name = sh3f.stem
    dest = assets_dir / "sh3d" / lib_name
    marker = dest / ".extracted"
    if not marker.exists():
        tmp = dest.with_name(dest.name + ".partial")
        shutil.rmtree(tmp, ignore_errors=True)
        try:
            with zipfile.ZipFile(sh3f) as z:
                z.extractall(tmp)
        except (zipfile.BadZipFile, OSError) as e:
            raise AssetError(f"cannot extract {sh3f}: {e}") from e
        shutil.rmtree(dest, ignore_errors=True)
        tmp.rename(dest)
        marker.write_text(str(sh3f.stat().st_size))
    props_path = dest / "PluginFurnitureCatalog.properties"
    if not props_path.exists():
        raise AssetError(f"{sh3f} has no PluginFurnitureCatalog.properties")
    text = props_path.read_text(encoding="latin-1")
    header = [ln[1:].strip() for ln in text.splitlines() if ln.startswith("#")]
    props = parse_properties(text)
    license_txt = ""
    lic = dest / "LICENSE.TXT"
    if lic.exists():
        license_txt = lic.read_text(encoding="utf-8", errors="replace").replace("\r\n", "\n")
    models = []
    n = 1
    while f"id#{n}" in props:

        def k(name: str, n: int = n) -> str:
            return f"{name}#{n}"

        model_rel = props.get(k("model"), "").lstrip("/")
        obj = dest / model_rel
        if model_rel and obj.suffix.lower() == ".obj" and obj.exists():
            rot = props.get(k("modelRotation"))
            rotation = [float(x) for x in rot.split()] if rot else None
            if rotation is not None and len(rotation) != 9:
                raise AssetError(f"{sh3f}: modelRotation#{n} has {len(rotation)} values, expected 9")
            models.append(
                {
                    "id": props[k("id")],
                    "name": props.get(k("name"), ""),
                    "category": props.get(k("category"), ""),
                    "obj": str(obj.relative_to(assets_dir)),
                    # Sweet Home 3D sizes are centimetres: width (x), depth, height (up).
                    "size_m": [
                        _float(props, k("width"), 100.0) / 100.0,
                        _float(props, k("depth"), 100.0) / 100.0,
                        _float(props, k("height"), 100.0) / 100.0,
                    ],
                    "elevation_m": (_float(props, k("elevation"), 0.0) or 0.0) / 100.0,
                    "model_rotation": rotation,
                    "door_or_window": props.get(k("doorOrWindow"), "false") == "true",
                    "movable": props.get(k("movable"), "true") == "true",
                    "staircase": k("staircaseCutOutShape") in props,
                    "creator": props.get(k("creator"), ""),
                    "library": lib_name,
                }
            )
        n += 1
    return {
        "library": lib_name,
        "name": props.get("name", lib_name),
        "license": props.get("license", ""),
        "provider": props.get("provider", ""),
        "version": props.get("version", ""),
        "header": header,
        "license_text": license_txt,
        "models": models,
    }


def texture_wanted(name: str, size: int) -> bool:
    """A color texture of a surface (no normal, gloss or glow map, no effect,
    trim or sign), at least 20 kB."""
    n = name.lower()
    return (
        n.startswith("textures/")
        and n.endswith((".jpg", ".tga"))
        and any(w in n for w in _TEXTURE_WORDS)
        and not any(x in n for x in _TEXTURE_SKIP)
        and size >= 20000
    )


def ensure_textures(assets_dir: Path = ASSETS_DIR) -> list[dict]:
    """The photo textures (downloaded and extracted once); ``[]`` with a
    note when the package cannot be fetched (the generator then uses its
    procedural materials alone)."""
    out_dir = assets_dir / "textures" / "nexuiz"
    index = out_dir / "index.json"
    if index.exists():
        return json.loads(index.read_text())
    if shutil.which("apt-get") is None or shutil.which("dpkg-deb") is None:
        print(f"assets: apt-get/dpkg-deb not found: no {TEXTURE_PACKAGE} textures", flush=True)
        return []
    with tempfile.TemporaryDirectory() as tmp_s:
        tmp = Path(tmp_s)
        r = subprocess.run(
            ["apt-get", "download", TEXTURE_PACKAGE],
            cwd=tmp,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        debs = sorted(tmp.glob("*.deb"))
        if r.returncode != 0 or not debs:
            print(f"assets: apt-get download {TEXTURE_PACKAGE} failed (exit {r.returncode}): no textures", flush=True)
            return []
        x = tmp / "x"
        subprocess.run(["dpkg-deb", "-x", str(debs[0]), str(x)], check=True)
        pk3 = next(x.rglob("textures.pk3"), None)
        if pk3 is None:
            raise AssetError(f"{debs[0].name} holds no textures.pk3")
        staging = out_dir.with_suffix(".tmp")
        shutil.rmtree(staging, ignore_errors=True)
        staging.mkdir(parents=True)
        entries = []
        with zipfile.ZipFile(pk3) as z:
            for info in z.infolist():
                if not texture_wanted(info.filename, info.file_size):
                    continue
                name = info.filename[len("textures/") :].replace("/", "__")
                (staging / name).write_bytes(z.read(info))
                entries.append(
                    {
                        "name": info.filename,
                        "path": str(out_dir / name),
                        "package": TEXTURE_PACKAGE,
                        "license": TEXTURE_LICENSE,
                    }
                )
        (staging / "index.json").write_text(json.dumps(entries, indent=1))
        shutil.rmtree(out_dir, ignore_errors=True)
        staging.rename(out_dir)
    print(f"assets: {len(entries)} textures from {TEXTURE_PACKAGE} -> {out_dir}", flush=True)
    return entries


def hdri_dir() -> Path | None:
    """Blender's bundled HDRIs, found through bpy when importable, else beside it."""
    try:
        import bpy  # type: ignore

        return Path(bpy.utils.system_resource("DATAFILES")) / "studiolights" / "world"
    except ImportError:
        pass
    for root in (TRAINING_DIR.parent / ".venv-bpy").glob("lib/python3*/site-packages/bpy/*/datafiles"):
        return root / "studiolights" / "world"
    return None


def write_attribution(libraries: list[dict], path: Path, textures: int = 0) -> None:
    """Writes the attribution page: per library its license, copyright and
    model creators; the photo textures (``textures`` of them) when used."""
    lines = [
        "# Attribution of the training assets",
        "",
        "Generated by `python -m training.synth.assets`; do not edit by hand.",
        "The rendered training data (not committed) is derived from these works.",
        "",
        "## Furniture: Debian package `sweethome3d-furniture`",
        "",
        "Sweet Home 3D furniture libraries (`/usr/share/sweethome3d/furniture/*.sh3f`),",
        "converted to OBJ by Emmanuel Puybaret / eTeks. Each library keeps its own license.",
        "",
    ]
    for lib in libraries:
        creators: dict[str, int] = {}
        for m in lib["models"]:
            creators[m["creator"] or "unknown"] = creators.get(m["creator"] or "unknown", 0) + 1
        lines += [
            f"### {lib['name']} (`{lib['library']}.sh3f`, version {lib['version']})",
            "",
            f"- License: {lib['license'] or 'see LICENSE.TXT in the library'}",
            f"- Provider: {lib['provider']}",
            f"- Models: {len(lib['models'])}",
            "- Creators: " + ", ".join(f"{c} ({n})" for c, n in sorted(creators.items())),
            "",
        ]
        hdr = [h for h in lib["header"] if h and "PluginFurnitureCatalog" not in h]
        if hdr:
            lines += ["Library notice:", ""] + [f"> {h}" for h in hdr] + [""]
        lic = lib["license_text"].strip().splitlines()
        if lic:
            lines += ["LICENSE.TXT (first lines):", "", "```"] + lic[:12] + ["```", ""]
    if textures:
        lines += [
            f"## Floor and wall textures: Debian package `{TEXTURE_PACKAGE}`",
            "",
            f"{textures} color textures of floors, walls, metal, stone and wood from the package's",
            "`textures.pk3` (normal, gloss and glow maps, effects and signs left out), in",
            f"`training/assets/textures/nexuiz/`. License: {TEXTURE_LICENSE}; copyright {TEXTURE_COPYRIGHT}.",
            "Half of the floors and walls of scenes rendered with this catalog use one of them.",
            "",
        ]
    lines += [
        "## Environment lighting: Blender's bundled HDRIs",
        "",
        "`bpy/<version>/datafiles/studiolights/world/*.exr`, shipped with Blender:",
        "CC0, created by Greg Zaal (Poly Haven).",
        "",
    ]
    d = hdri_dir()
    lic = d / "license.txt" if d else None
    if lic and lic.exists():
        lines += ["```"] + lic.read_text().strip().splitlines() + ["```", ""]
    tmp = path.with_suffix(".tmp")
    tmp.write_text("\n".join(lines))
    tmp.replace(path)


def prepare(assets_dir: Path = ASSETS_DIR, attribution: Path | None = TRAINING_DIR / "ATTRIBUTION.md") -> Path:
    """Installs and extracts everything; returns the catalog path."""
    assets_dir.mkdir(parents=True, exist_ok=True)
    catalog_path = assets_dir / "catalog.json"
    libs = [extract_library(p, assets_dir) for p in ensure_package()]
    catalog = {
        "version": CATALOG_VERSION,
        "assets_dir": str(assets_dir),
        "hdri_dir": str(hdri_dir() or ""),
        "libraries": [{k: v for k, v in lib.items() if k not in ("models", "license_text", "header")} for lib in libs],
        "models": [m for lib in libs for m in lib["models"]],
        "textures": ensure_textures(assets_dir),
    }
    if not catalog["models"]:
        raise AssetError(f"no usable OBJ model found under {assets_dir / 'sh3d'}")
    tmp = catalog_path.with_suffix(".tmp")
    tmp.write_text(json.dumps(catalog, indent=1))
    tmp.replace(catalog_path)
    if attribution is not None:
        write_attribution(libs, attribution, len(catalog["textures"]))
    return catalog_path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--assets", type=Path, default=ASSETS_DIR, help="where to extract (default: training/assets)")
    ap.add_argument("--no-attribution", action="store_true", help="do not rewrite training/ATTRIBUTION.md")
    args = ap.parse_args(argv)
    try:
        path = prepare(args.assets, None if args.no_attribution else TRAINING_DIR / "ATTRIBUTION.md")
    except AssetError as e:
        print(f"assets: error: {e}", file=sys.stderr)
        return 1
    cat = json.loads(path.read_text())
    print(
        f"assets: {len(cat['models'])} models from {len(cat['libraries'])} libraries, "
        f"{len(cat.get('textures', []))} textures -> {path}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
