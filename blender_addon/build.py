#!/usr/bin/env python3
"""Package the Blender extension: one installable zip for this platform.

The zip holds the add-on modules, ``blender_manifest.toml`` (with its
``wheels`` list filled in) and ``wheels/``:

- ``harmonizer-<version>-py3-none-linux_x86_64.whl``: the Python binding
  (``ffi/python/harmonizer``) with ``libharmonizer.so`` inside the package
  (``harmonizer/lib/``, the layout of the wheel ``scripts/wheels.sh`` builds),
  built here from the files (no build backend needed), or that wheel itself
  (``--binding-wheel dist/harmonizer-*.whl``, tagged ``manylinux_*_x86_64``);
- ``onnxruntime-1.31.*-cp311-...manylinux...whl``: fetched with
  ``pip download`` (ONNX Runtime for the neural backend; the add-on only loads
  its shared library), or given (``--onnxruntime-wheel FILE``, offline);
- ``pyoidn-2.*-py3-none-manylinux2014_x86_64.whl``: fetched the same way
  (Intel Open Image Denoise for the denoise stage; the add-on only locates its
  shared library and hands its path to libharmonizer), or given
  (``--oidn-wheel FILE``).

Only the zip is written, into ``--out`` (default ``dist/``); the staging and
the downloads live in a temporary directory (``--cache DIR`` keeps the
downloaded wheels between builds). With ``--binding-wheel`` (or ``--lib``),
``--onnxruntime-wheel`` and ``--oidn-wheel`` the build needs no network.

Usage::

    python blender_addon/build.py [--lib target/release/libharmonizer.so | --binding-wheel WHL]
                                  [--cargo] [--out dist/] [--cache DIR]
                                  [--onnxruntime-wheel WHL | --no-onnxruntime]
                                  [--oidn-wheel WHL | --no-oidn]

Blender installs the zip with Edit > Preferences > Get Extensions > Install
from Disk, or ``blender --command extension install-file -r user_default <zip>``.
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import os
import re
import shutil
import subprocess
import sys
import tempfile
import zipfile

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
BINDING = os.path.join(REPO, "ffi", "python", "harmonizer")
ORT_SPEC = "onnxruntime==1.31.*"
#: Open Image Denoise 2.x (the release libharmonizer's denoise stage is built for).
OIDN_SPEC = "pyoidn==2.*"
ADDON_FILES_EXCLUDE = {"build.py"}
WHEEL_PLATFORM = "linux_x86_64"


def _linux_x64_wheel(path: str) -> bool:
    """Whether a wheel's platform tags include Linux x86_64: ``linux_x86_64``
    (a local build) or a manylinux tag (``scripts/wheels.sh``'s, repaired by
    auditwheel), which Blender maps to ``linux-x64`` alike."""
    platforms = os.path.basename(path)[: -len(".whl")].split("-")[-1].split(".")
    return any(re.fullmatch(r"(many)?linux[0-9_]*_x86_64", p) for p in platforms)


def _manifest_version(text: str) -> str:
    m = re.search(r'^version\s*=\s*"([^"]+)"', text, re.M)
    if not m:
        raise SystemExit("blender_manifest.toml has no version")
    return m.group(1)


def _record_line(arcname: str, data: bytes) -> str:
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
    return f"{arcname},sha256={digest},{len(data)}"


def build_binding_wheel(lib: str, version: str, out_dir: str) -> str:
    """A wheel of the ctypes binding with libharmonizer inside the package."""
    if not os.path.isfile(os.path.join(BINDING, "__init__.py")):
        raise SystemExit(f"Python binding not found: {BINDING}/__init__.py")
    name = f"harmonizer-{version}-py3-none-{WHEEL_PLATFORM}.whl"
    path = os.path.join(out_dir, name)
    dist_info = f"harmonizer-{version}.dist-info"
    files: list[tuple[str, bytes]] = []
    for root, dirs, fnames in os.walk(BINDING):
        dirs[:] = sorted(d for d in dirs if d != "__pycache__")
        for fn in sorted(fnames):
            if fn.endswith((".pyc", ".so")) or fn.startswith("."):
                continue
            full = os.path.join(root, fn)
            arc = os.path.join("harmonizer", os.path.relpath(full, BINDING)).replace(os.sep, "/")
            with open(full, "rb") as fh:
                files.append((arc, fh.read()))
    with open(lib, "rb") as fh:
        files.append(("harmonizer/lib/libharmonizer.so", fh.read()))
    metadata = (
        "Metadata-Version: 2.1\n"
        f"Name: harmonizer\nVersion: {version}\n"
        "Summary: Python binding of libharmonizer (bundled library)\n"
        "License: Apache-2.0\nRequires-Python: >=3.9\nRequires-Dist: numpy\n"
    ).encode()
    wheel = (
        "Wheel-Version: 1.0\nGenerator: harmonizer blender_addon/build.py\n"
        f"Root-Is-Purelib: false\nTag: py3-none-{WHEEL_PLATFORM}\n"
    ).encode()
    files.append((f"{dist_info}/METADATA", metadata))
    files.append((f"{dist_info}/WHEEL", wheel))
    record = "\n".join(_record_line(a, d) for a, d in files) + f"\n{dist_info}/RECORD,,\n"
    files.append((f"{dist_info}/RECORD", record.encode()))
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for arc, data in files:
            info = zipfile.ZipInfo(arc, date_time=(2026, 1, 1, 0, 0, 0))
            info.external_attr = (0o755 if arc.endswith(".so") else 0o644) << 16
            info.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(info, data)
    return path


def fetch_wheel(spec: str, prefix: str, cache: str) -> str:
    """The cp311 manylinux x86_64 wheel of ``spec`` (file names starting ``prefix``), from the cache or ``pip download``."""
    os.makedirs(cache, exist_ok=True)

    def cached() -> list[str]:
        return sorted(f for f in os.listdir(cache) if f.startswith(prefix) and f.endswith(".whl"))

    have = cached()
    if not have:
        cmd = [
            sys.executable,
            "-m",
            "pip",
            "download",
            spec,
            "--no-deps",
            "--only-binary=:all:",
            "--python-version",
            "3.11",
            "--implementation",
            "cp",
            "--abi",
            "cp311",
            "--platform",
            "manylinux_2_28_x86_64",
            "--platform",
            "manylinux_2_27_x86_64",
            "--platform",
            "manylinux2014_x86_64",
            "-d",
            cache,
        ]
        print("+", " ".join(cmd), flush=True)
        subprocess.run(cmd, check=True)
        have = cached()
    if not have:
        raise SystemExit(f"pip download {spec} produced no wheel in {cache}")
    return os.path.join(cache, have[-1])


def given_wheel(path: str, prefix: str, option: str) -> str:
    """A wheel file the caller gave (``--onnxruntime-wheel`` and the like): it must exist and be ``prefix*.whl``."""
    path = os.path.abspath(path)
    name = os.path.basename(path)
    if not os.path.isfile(path):
        raise SystemExit(f"{option}: {path} not found")
    if not (name.startswith(prefix) and name.endswith(".whl")):
        raise SystemExit(f"{option}: {name} is not a {prefix}*.whl wheel")
    return path


def fetch_onnxruntime(cache: str) -> str:
    """The onnxruntime cp311 manylinux wheel, from the cache or ``pip download``."""
    return fetch_wheel(ORT_SPEC, "onnxruntime-1.31.", cache)


def fetch_pyoidn(cache: str) -> str:
    """The pyoidn 2.x manylinux wheel (Open Image Denoise's library inside), from the cache or ``pip download``."""
    return fetch_wheel(OIDN_SPEC, "pyoidn-2.", cache)


def stage_addon(stage: str, wheels: list[str]) -> None:
    """Copy the add-on modules and write the manifest with its wheels."""
    if os.path.isdir(stage):
        shutil.rmtree(stage)
    os.makedirs(os.path.join(stage, "wheels"))
    for fn in sorted(os.listdir(HERE)):
        full = os.path.join(HERE, fn)
        if fn in ADDON_FILES_EXCLUDE or not os.path.isfile(full):
            continue
        if fn.endswith(".py") or fn in {"README.md", "LICENSE"}:
            shutil.copy2(full, os.path.join(stage, fn))
    for w in wheels:
        shutil.copy2(w, os.path.join(stage, "wheels", os.path.basename(w)))
    with open(os.path.join(HERE, "blender_manifest.toml"), encoding="utf-8") as fh:
        manifest = fh.read()
    listed = ", ".join(f'"./wheels/{os.path.basename(w)}"' for w in wheels)
    manifest, n = re.subn(r"^wheels\s*=\s*\[[^\]]*\]", f"wheels = [{listed}]", manifest, flags=re.M)
    if n != 1:
        raise SystemExit("blender_manifest.toml: expected one 'wheels = [...]' line")
    # The staged tree holds only what ships: drop the source-tree build exclusions.
    manifest = re.sub(r"\n\[build\]\n(?:[^\[].*\n?)*", "\n", manifest)
    with open(os.path.join(stage, "blender_manifest.toml"), "w", encoding="utf-8") as fh:
        fh.write(manifest)


def write_zip(stage: str, path: str) -> None:
    """Zip the staged tree (files at the archive root), atomically."""
    tmp = path + ".tmp"
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as zf:
        for root, dirs, fnames in os.walk(stage):
            dirs.sort()
            for fn in sorted(fnames):
                full = os.path.join(root, fn)
                arc = os.path.relpath(full, stage).replace(os.sep, "/")
                # Wheels are already compressed.
                zf.write(full, arc, compress_type=zipfile.ZIP_STORED if fn.endswith(".whl") else zipfile.ZIP_DEFLATED)
    os.replace(tmp, path)


def validate(path: str) -> None:
    """Run Blender's own extension validator on the zip when it is available."""
    try:
        import importlib.util

        spec = importlib.util.find_spec("bpy")
    except Exception:
        spec = None
    if spec is None or not spec.submodule_search_locations:
        print("note: bpy not importable here; skipping Blender's manifest validation")
        return
    root = list(spec.submodule_search_locations)[0]
    candidates = [
        os.path.join(root, d, "scripts", "addons_core", "bl_pkg", "cli", "blender_ext.py")
        for d in sorted(os.listdir(root))
        if re.fullmatch(r"\d+\.\d+", d)
    ]
    tool = next((c for c in candidates if os.path.isfile(c)), None)
    if tool is None:
        print("note: Blender's blender_ext.py not found; skipping manifest validation")
        return
    subprocess.run([sys.executable, tool, "validate", path], check=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--lib",
        default=os.environ.get("HARMONIZER_LIB") or os.path.join(REPO, "target", "release", "libharmonizer.so"),
        help="libharmonizer.so to bundle (default: $HARMONIZER_LIB or target/release)",
    )
    ap.add_argument("--cargo", action="store_true", help="build it first: cargo build --release -p harmonizer-ffi")
    ap.add_argument(
        "--binding-wheel",
        metavar="WHL",
        help="bundle this harmonizer wheel (scripts/wheels.sh's dist/harmonizer-*.whl) instead of building one from --lib",
    )
    ap.add_argument("--out", default=os.path.join(REPO, "dist"), help="output folder for the zip (the only thing written)")
    ap.add_argument(
        "--cache",
        metavar="DIR",
        help="keep downloaded wheels here between builds (default: a temporary directory; pip's cache still serves)",
    )
    ap.add_argument("--onnxruntime-wheel", metavar="WHL", help=f"bundle this {ORT_SPEC} wheel (no download)")
    ap.add_argument("--oidn-wheel", metavar="WHL", help=f"bundle this {OIDN_SPEC} wheel (no download)")
    ap.add_argument("--no-onnxruntime", action="store_true", help="do not bundle onnxruntime (classical/bypass only)")
    ap.add_argument(
        "--no-oidn",
        action="store_true",
        help="do not bundle Open Image Denoise (pyoidn; the denoise stage then needs one installed)",
    )
    ap.add_argument("--no-validate", action="store_true", help="skip Blender's manifest validation")
    args = ap.parse_args(argv)

    if args.no_onnxruntime and args.onnxruntime_wheel:
        ap.error("--no-onnxruntime and --onnxruntime-wheel exclude each other")
    if args.no_oidn and args.oidn_wheel:
        ap.error("--no-oidn and --oidn-wheel exclude each other")
    with open(os.path.join(HERE, "blender_manifest.toml"), encoding="utf-8") as fh:
        version = _manifest_version(fh.read())
    if args.binding_wheel:
        binding = given_wheel(args.binding_wheel, f"harmonizer-{version}-", "--binding-wheel")
        if not _linux_x64_wheel(binding):
            raise SystemExit(f"--binding-wheel: {os.path.basename(binding)} is not a Linux x86_64 wheel")
    else:
        if args.cargo:
            subprocess.run(["cargo", "build", "--release", "-p", "harmonizer-ffi"], cwd=REPO, check=True)
        lib = os.path.abspath(args.lib)
        if not os.path.isfile(lib):
            print(
                f"error: {lib} not found; build it with `cargo build --release -p harmonizer-ffi` or pass "
                "--lib/--cargo/--binding-wheel",
                file=sys.stderr,
            )
            return 2
    # Nothing but the zip goes outside this temporary directory.
    with tempfile.TemporaryDirectory(prefix="harmonizer-blender-") as work:
        cache = os.path.abspath(args.cache) if args.cache else os.path.join(work, "downloads")
        wheel_dir = os.path.join(work, "wheels")
        os.makedirs(wheel_dir)
        wheels = [binding if args.binding_wheel else build_binding_wheel(lib, version, wheel_dir)]
        if args.onnxruntime_wheel:
            wheels.append(given_wheel(args.onnxruntime_wheel, "onnxruntime-1.31.", "--onnxruntime-wheel"))
        elif not args.no_onnxruntime:
            wheels.append(fetch_onnxruntime(cache))
        if args.oidn_wheel:
            wheels.append(given_wheel(args.oidn_wheel, "pyoidn-2.", "--oidn-wheel"))
        elif not args.no_oidn:
            wheels.append(fetch_pyoidn(cache))
        stage = os.path.join(work, "stage")
        stage_addon(stage, wheels)
        os.makedirs(args.out, exist_ok=True)
        zip_path = os.path.join(os.path.abspath(args.out), f"harmonizer-{version}-linux-x64.zip")
        write_zip(stage, zip_path)
    if not args.no_validate:
        validate(zip_path)
    print(zip_path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
