"""``usd-harmonize``: enhance the render products of a USD stage.

usd-harmonize STAGE [--settings PRIM] [--product NAME] [--frames 1001-1024 [--preroll N]]
              [--out-dir DIR] [--layer FILE | --in-place | --no-layer]
              [--backend auto|neural|classical|bypass] [--param NAME=VALUE]
              [--denoise auto|on|off|temporal] [--denoise-quality high|balanced|fast]
              [--samples N] [--map VAR=ROLE] [--motion-scale SX,SY] [--ocio CONFIG]
              [--light-direction X,Y,Z | --no-light]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from . import binding
from .errors import UsdHarmonizerError
from .frames import parse_frame_range
from .light import parse_direction
from .process import Options
from .run import run_stage
from .settings import ProductInfo, check_denoise_param


def _pairs(items: list[str], flag: str) -> dict[str, str]:
    out = {}
    for it in items:
        if "=" not in it:
            raise UsdHarmonizerError(f"{flag} {it!r}: expected NAME=VALUE")
        k, v = it.split("=", 1)
        out[k.strip()] = v.strip()
    return out


def add_cmdline_args(parser: argparse.ArgumentParser) -> None:
    """Adds the shared options (also usable by pipeline tools wrapping this one)."""
    parser.add_argument(
        "--settings",
        metavar="PRIM",
        help="RenderSettings prim path (default: the stage's)",
    )
    parser.add_argument(
        "--product",
        action="append",
        metavar="NAME",
        help="product name or path (repeatable; default: all)",
    )
    parser.add_argument(
        "--frames",
        metavar="RANGE",
        help="frames, e.g. 1001-1024, 1001-1024x2, 1001,1005 (default: the stage's range)",
    )
    parser.add_argument(
        "--preroll",
        type=int,
        default=0,
        metavar="N",
        help="process the N frames before the first of --frames first, without writing "
        "them, so a chunk of a shot starts with the temporal state of a sequential run "
        "(needs --frames; fewer at the start of the shot)",
    )
    parser.add_argument(
        "--out-dir",
        type=Path,
        metavar="DIR",
        help="output directory; each product's files go to DIR/<product prim name>/ "
        "(default: harmonized/ beside each product's files)",
    )
    parser.add_argument(
        "--base-dir",
        type=Path,
        metavar="DIR",
        help="directory relative productNames resolve against (default: the stage's)",
    )
    g = parser.add_mutually_exclusive_group()
    g.add_argument(
        "--layer",
        type=Path,
        metavar="FILE",
        help="layer to write (default: <stage>.harmonized.usda)",
    )
    g.add_argument(
        "--in-place",
        action="store_true",
        help="add the new products to the stage's root layer",
    )
    g.add_argument("--no-layer", action="store_true", help="write no layer")
    parser.add_argument(
        "--backend", default="auto", choices=["auto", "neural", "classical", "bypass"]
    )
    parser.add_argument(
        "--strength", type=float, help="blend of enhanced over input, 0..1"
    )
    parser.add_argument(
        "--context-frames", type=int, help="previous enhanced frames used, 0..8"
    )
    parser.add_argument(
        "--denoise",
        choices=["auto", "on", "off", "temporal"],
        help="denoise with Open Image Denoise before enhancing (default: the stage's "
        "harmonizer:denoise, else auto: on for 1-64 samples, else the first frame's noise decides)",
    )
    parser.add_argument(
        "--denoise-quality",
        choices=["high", "balanced", "fast"],
        help="Open Image Denoise quality (default: the stage's harmonizer:denoiseQuality, else high)",
    )
    parser.add_argument(
        "--samples",
        type=int,
        metavar="N",
        help="samples per pixel the frames were rendered with (default: the stage's "
        "harmonizer:samples, else 0 = unknown); 0 for frames the renderer already denoised",
    )
    light = parser.add_mutually_exclusive_group()
    light.add_argument(
        "--light-direction",
        metavar="X,Y,Z",
        help="direction toward the light (stage world space) for every frame, for inserts' "
        "cast shadows (default: harmonizer:lightDirection on the product or settings prim, "
        "else the stage's brightest DistantLight at each frame)",
    )
    light.add_argument(
        "--no-light",
        action="store_true",
        help="pass no light direction: inserts cast no directional shadow",
    )
    parser.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="any session parameter (repeatable)",
    )
    parser.add_argument(
        "--map",
        action="append",
        default=[],
        metavar="VAR=ROLE",
        help="map a RenderVar to color, depth, motion, normal, coverage, insert_mask, insert_id, albedo, "
        "denoise_normal or ignore",
    )
    parser.add_argument(
        "--motion-scale",
        metavar="SX,SY",
        help="motion-vector scale for every product, e.g. 1,-1 for +y up",
    )
    parser.add_argument(
        "--ocio",
        metavar="CONFIG",
        help="OCIO config (default: $OCIO, else ocio://default)",
    )
    parser.add_argument(
        "--threads", type=int, default=0, help="library threads (0 = all cores)"
    )
    parser.add_argument(
        "--model", metavar="FILE", help="ONNX model (default: the embedded one)"
    )
    parser.add_argument(
        "--ort-library",
        metavar="FILE",
        help="libonnxruntime.so (default: $HARMONIZER_ORT_LIB, else the library's search)",
    )


def _options(args: argparse.Namespace) -> Options:
    params: dict[str, Any] = {
        k: binding.load().parse_param(v) for k, v in _pairs(args.param, "--param").items()
    }
    if args.strength is not None:
        params["strength"] = args.strength
    if args.context_frames is not None:
        params["context_frames"] = args.context_frames
    for name, value, flag in (
        ("denoise", args.denoise, "--denoise"),
        ("denoise_quality", args.denoise_quality, "--denoise-quality"),
        ("samples", args.samples, "--samples"),
    ):
        if value is not None:
            params[name] = check_denoise_param(name, value, flag)
    ms = None
    if args.motion_scale:
        try:
            sx, sy = (float(x) for x in args.motion_scale.split(","))
        except ValueError:
            raise UsdHarmonizerError(
                f"--motion-scale {args.motion_scale!r}: expected SX,SY (e.g. 1,-1)"
            ) from None
        ms = (sx, sy)
    light: Any = "auto"
    if args.no_light:
        light = "none"
    elif args.light_direction is not None:
        light = parse_direction(args.light_direction, "--light-direction")
    return Options(
        light=light,
        backend=args.backend,
        params=params,
        out_dir=args.out_dir,
        user_map=_pairs(args.map, "--map"),
        motion_scale=ms,
        ocio_config=args.ocio,
        threads=args.threads,
        model=args.model,
        ort_library=args.ort_library,
    )


class _Progress:
    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.t0 = time.monotonic()

    def __call__(self, done: int, total: int, prod: ProductInfo, frame: int) -> None:
        if not self.enabled:
            return
        n = 30
        fill = n * done // max(total, 1)
        line = f"\r[{'#' * fill}{'.' * (n - fill)}] {done}/{total} {prod.name} frame {frame}  {time.monotonic() - self.t0:.1f}s"
        sys.stderr.write(line)
        if done == total:
            sys.stderr.write("\n")
        sys.stderr.flush()



def _ratio_text(r) -> str:
    """The summary's words for a frame's ``light_ratio``: the value and where
    it came from, or why the library measures it."""
    if r.light_ratio is not None:
        return f"{r.light_ratio:.2f} ({r.light_ratio_source})"
    why = "" if r.light_ratio_source == "none" else f"; {r.light_ratio_source}"
    return f"measured by the library{why}"

def main(argv: list[str] | None = None) -> int:
    """Entry point of ``usd-harmonize``; returns the exit status."""
    parser = argparse.ArgumentParser(
        prog="usd-harmonize", description=__doc__.split("\n")[0].split(": ", 1)[1]
    )
    parser.add_argument(
        "stage", type=Path, help="USD stage whose render products were rendered"
    )
    add_cmdline_args(parser)
    parser.add_argument(
        "--quiet", action="store_true", help="no progress bar or summary"
    )
    args = parser.parse_args(argv)
    try:
        options = _options(args)
        frames = parse_frame_range(args.frames) if args.frames else None
        summary = run_stage(
            args.stage,
            settings=args.settings,
            products=args.product,
            frames=frames,
            options=options,
            layer=args.layer,
            in_place=args.in_place,
            write_layer_file=not args.no_layer,
            base_dir=args.base_dir,
            on_frame=_Progress(not args.quiet and sys.stderr.isatty()),
            preroll=args.preroll,
        )
    except UsdHarmonizerError as e:
        print(f"usd-harmonize: error: {e}", file=sys.stderr)
        return 1
    if not args.quiet:
        for path, (prod, res) in summary.results.items():
            if not res:
                continue
            resets = (
                ", ".join(f"{r.frame} ({r.reset})" for r in res if r.reset) or "none"
            )
            ms = sum(r.total_ms for r in res) / len(res)
            wall = sum(r.timings.get("total", 0.0) for r in res) / len(res)
            warns = sum(len(r.warnings) for r in res)
            denoised = sum(r.denoised for r in res)
            decisions = [r.denoise_decision for r in res if r.denoise_decision]
            print(
                f"{path}: {len(res)} frames {res[0].frame}-{res[-1].frame}, backend {res[-1].backend}, "
                f"color space {res[-1].color_space}, inputs {'+'.join(res[-1].inputs)}, "
                f"{ms:.1f} ms/frame in the library, {wall:.1f} ms/frame in all, "
                f"resets: {resets}, warnings: {warns}, denoised: {denoised}"
                + (f" ({decisions[-1]})" if decisions else "")
                + f", light: {res[-1].light_source}"
                + f", light ratio: {_ratio_text(res[-1])}"
                + f"\n  -> {res[0].output.parent}"
            )
        if summary.preroll_frames:
            print(
                f"pre-roll: {summary.preroll_frames} frame(s) before the first, "
                "processed and not written"
            )
        if summary.layer:
            print(f"layer: {summary.layer}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
