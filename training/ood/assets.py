"""Fetches the out-of-domain benchmark's textures from Debian packages never used in training.

    python3 -m training.ood.assets            # -> training/ood/assets/ (idempotent)

``apt-get download`` (no root needed) fetches two packages into
``.cache/ood-debs/``, ``dpkg-deb -x`` unpacks them, and the textures listed in
``TEXTURES`` are copied to ``training/ood/assets/``. Sources and licences are
recorded in ``training/ood/ATTRIBUTION.md``. The training set uses Sweet Home
3D furniture and Blender's bundled HDRIs; this set uses neither (see
``../shared/DATA.md`` for the reserved sources, which it does not use either).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
ASSETS = Path(__file__).resolve().parent / "assets"

PACKAGES = {
    "etr": ("extremetuxracer-data", "usr/share/games/etr/terrains"),
    "oa": ("openarena-081-textures", "usr/share/games/openarena/baseoa/pak4-textures.pk3"),
}

# name in assets/ -> (package key, path inside the package's directory or pk3)
TEXTURES = {
    "grass.png": ("etr", "grass02.png"),
    "pave.png": ("etr", "pave01.png"),
    "rock.png": ("etr", "rock04.png"),
    "pebbles.png": ("etr", "pebbles04.png"),
    "mud.png": ("etr", "mud01.png"),
    "blocks.jpg": ("oa", "textures/gothic_block/blocks19.jpg"),
    "concrete.jpg": ("oa", "textures/base_wall/concrete_dark.jpg"),
    "tiles.jpg": ("oa", "textures/base_floor/tilefloor7_ow.jpg"),
    "rusted.jpg": ("oa", "textures/base_wall/rusted.jpg"),
    "bluemetal.jpg": ("oa", "textures/base_wall/bluemetal2.jpg"),
    "diamond.jpg": ("oa", "textures/base_floor/diamond2c.jpg"),
    "patch.jpg": ("oa", "textures/base_wall/patch10_beatup4.jpg"),
}


def _unpack(pkg: str, cache: Path) -> Path:
    root = cache / pkg
    if (root / ".done").exists():
        return root
    cache.mkdir(parents=True, exist_ok=True)
    debs = sorted(cache.glob(f"{pkg}_*.deb"))
    if not debs:
        p = subprocess.run(["apt-get", "download", pkg], cwd=cache, capture_output=True, text=True)
        debs = sorted(cache.glob(f"{pkg}_*.deb"))
        if not debs:
            raise RuntimeError(f"apt-get download {pkg} failed (exit {p.returncode}): {p.stderr.strip()[-500:]}")
    shutil.rmtree(root, ignore_errors=True)
    subprocess.run(["dpkg-deb", "-x", str(debs[-1]), str(root)], check=True)
    (root / ".done").write_text(debs[-1].name + "\n")
    return root


def fetch(out: Path = ASSETS, cache: Path = REPO / ".cache" / "ood-debs") -> Path:
    if all((out / n).exists() for n in TEXTURES):
        return out
    import zipfile

    out.mkdir(parents=True, exist_ok=True)
    roots = {k: _unpack(pkg, cache) for k, (pkg, _) in PACKAGES.items()}
    for name, (key, rel) in TEXTURES.items():
        base = roots[key] / PACKAGES[key][1]
        dst = out / name
        if base.suffix == ".pk3":
            with zipfile.ZipFile(base) as z:
                dst.write_bytes(z.read(rel))
        else:
            shutil.copyfile(base / rel, dst)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ASSETS)
    args = ap.parse_args(argv)
    try:
        d = fetch(args.out)
    except (RuntimeError, subprocess.CalledProcessError, KeyError, OSError) as e:
        print(f"ood.assets: {e}", file=sys.stderr)
        return 1
    print(f"ood.assets: {len(TEXTURES)} textures in {d}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
