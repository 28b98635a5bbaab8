"""Real assets for the data generator: Sweet Home 3D furniture and Blender's HDRIs.

``python -m training.synth.assets`` (any Python 3.9+, no bpy needed) makes sure
the Debian package ``sweethome3d-furniture`` is installed (``apt-get`` when run as
root), extracts each ``.sh3f`` library into ``training/assets/sh3d/<library>/``,
writes ``training/assets/catalog.json`` (one entry per model: OBJ path, size in
metres, elevation, rotation, library, creator, license) and regenerates
``training/ATTRIBUTION.md``. Every step is idempotent: finished work is skipped.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

TRAINING_DIR = Path(__file__).resolve().parent.parent
ASSETS_DIR = TRAINING_DIR / "assets"
SH3D_SYSTEM_DIR = Path("/usr/share/sweethome3d/furniture")
DEBIAN_PACKAGE = "sweethome3d-furniture"
CATALOG_VERSION = 1


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


def write_attribution(libraries: list[dict], path: Path) -> None:
    """Writes the attribution page: per library its license, copyright and model creators."""
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
    }
    if not catalog["models"]:
        raise AssetError(f"no usable OBJ model found under {assets_dir / 'sh3d'}")
    tmp = catalog_path.with_suffix(".tmp")
    tmp.write_text(json.dumps(catalog, indent=1))
    tmp.replace(catalog_path)
    if attribution is not None:
        write_attribution(libs, attribution)
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
    print(f"assets: {len(cat['models'])} models from {len(cat['libraries'])} libraries -> {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
