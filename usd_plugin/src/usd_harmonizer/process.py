"""The processing loop: one harmonizer session per render product (and its
camera), frames in increasing order, outputs written atomically.

For each frame: read the product's file, find each var's channels by name,
convert color to Linear Rec.709 (PyOpenColorIO), pass depth, motion
(scaled into the library's convention), normals, coverage, the insert mask,
the denoise stage's albedo (converted like the color) and normal, the
frame's camera matrices (so a product without motion vectors is
reprojected from depth) and the direction toward the frame's dominant
light (:mod:`usd_harmonizer.light`, for inserts' cast shadows), enhance,
convert back, and write a copy of the file with the color (and coverage)
channels replaced and ``harmonizer:*`` attributes added. A failed frame
raises :class:`FrameError` naming the product, frame and file, and leaves
the session's temporal state unchanged.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from . import binding
from .camera import exr_matrices
from .color import ColorConverter, converter_for
from .errors import FrameError, ProductFileError, SettingsError, UsdHarmonizerError
from .exrio import read_exr, write_exr_atomic
from .light import (
    NO_LIGHT,
    Light,
    is_dome,
    light_at,
    SceneLight,
    normalized,
    ratio_lights,
    scene_light_at,
)
from .settings import ProductInfo, SettingsInfo
from .varmap import Binding, find_channels, map_vars


@dataclass
class Options:
    """How products are processed (the CLI's options)."""

    #: Library backend: auto, neural, classical or bypass.
    backend: str = "auto"
    #: Further session parameters by name (``strength``, ``context_frames``,
    #: ``denoise``, ``denoise_quality``, ``samples``, ...); they win over the
    #: stage's ``harmonizer:denoise*`` / ``harmonizer:samples`` attributes.
    params: dict[str, Any] = field(default_factory=dict)
    #: Output directory: each product's files go to ``out_dir/<product prim
    #: name>/``; default ``<product file dir>/harmonized``.
    out_dir: Path | None = None
    #: User var mapping: var name or path -> role (or ``ignore``).
    user_map: dict[str, str] = field(default_factory=dict)
    #: Motion-vector scale for every product (overrides ``harmonizer:motionVectorScale``).
    motion_scale: tuple[float, float] | None = None
    #: OCIO config (default ``$OCIO``, else ``ocio://default``).
    ocio_config: str | None = None
    #: Library threads (0 = all cores).
    threads: int = 0
    #: Model file (None = the library's embedded default).
    model: str | None = None
    #: ONNX Runtime library (None = ``$HARMONIZER_ORT_LIB`` and the library's search).
    ort_library: str | None = None
    #: Pass the per-frame camera matrices even when motion vectors exist.
    always_cameras: bool = True
    #: The light inserts cast shadows away from (session parameter
    #: ``light_direction``, world space): ``"auto"`` (at each frame,
    #: ``harmonizer:lightDirection`` on the product or the settings prim,
    #: else the stage's brightest DistantLight; see
    #: :mod:`usd_harmonizer.light`), ``"none"`` (no cast shadows), or a
    #: direction (x, y, z) toward the light in the stage's world space for
    #: every frame. A ``light_direction`` in :attr:`params` wins over all.
    light: str | tuple[float, float, float] = "auto"


@dataclass
class FrameResult:
    """What happened to one frame of one product."""

    product: str
    frame: int
    source: Path
    output: Path
    reset: str | None
    backend: str
    total_ms: float
    history_used: int
    color_space: str
    inputs: list[str]
    warnings: list[str]
    #: Host-side times in ms: read, color (both conversions), library, write.
    timings: dict[str, float] = field(default_factory=dict)
    #: USD color space token of ``color_space`` (``lin_ap1_scene``, ...), the
    #: new product's UsdColorSpaceAPI ``colorSpace:name``; None when the
    #: OCIO space has none.
    usd_color_space: str | None = None
    #: Whether the denoise stage denoised the frame.
    denoised: bool = False
    #: The denoise stage's decision, on the frame that made it (the first
    #: after a reset), else None.
    denoise_decision: str | None = None
    #: The measured noise level (``denoise auto`` without ``samples``), else None.
    noise_level: float | None = None
    #: A pre-roll frame (``--preroll``): processed to warm the temporal
    #: state, not written (``output`` is where it would have gone).
    preroll: bool = False
    #: The direction toward the light passed for this frame (unit, world
    #: space), or None; :attr:`light_source` says where it came from.
    light_direction: tuple[float, float, float] | None = None
    light_source: str = "none"
    #: The ``light_ratio`` passed for this frame (None: the library measured
    #: it) and where it came from (:func:`usd_harmonizer.light.light_ratio_at`).
    light_ratio: float | None = None
    light_ratio_source: str = "none"


def make_device(options: Options) -> Any:
    """A library device for ``options`` (threads, model)."""
    hz = binding.load()
    try:
        return hz.Device(
            threads=options.threads,
            model=options.model,
            ort_library=options.ort_library,
        )
    except hz.HarmonizerError as e:
        raise UsdHarmonizerError(f"cannot create the harmonizer device: {e}") from e


def _header_matrix(attrs: dict[str, Any], name: str) -> np.ndarray | None:
    v = attrs.get(name)
    if v is None:
        return None
    try:
        m = np.asarray(v, dtype=np.float64).reshape(4, 4)
    except (TypeError, ValueError):
        return None
    return m if np.isfinite(m).all() else None


#: Depth the library expects where nothing was hit.
FAR_DEPTH = 1e10


def empty_depth_to_far(depth: np.ndarray) -> np.ndarray:
    """A float32 copy with empty pixels as the library expects them: renderers
    write 0, a negative value, infinity or NaN where nothing was hit; all of
    them become a very large depth (1e10)."""
    d = np.array(depth, dtype=np.float32)
    d[~(np.isfinite(d) & (d > 0))] = FAR_DEPTH
    return d


def data_window_matrix(spec: Any) -> np.ndarray:
    """Maps NDC of the display window to NDC of the data window (the pixels
    the library sees), for overscan or cropped renders; identity otherwise."""
    x, y, w, h = spec.x, spec.y, spec.width, spec.height
    fx, fy, fw, fh = spec.full_x, spec.full_y, spec.full_width, spec.full_height
    m = np.eye(4)
    m[0, 0], m[1, 1] = fw / w, fh / h
    m[3, 0], m[3, 1] = (fx - x) / w, (fy - y) / h
    return m


def output_path(product: ProductInfo, frame: int, out_dir: Path | None) -> Path:
    """Where the enhanced file of ``product``'s ``frame`` goes: beside the
    source in ``harmonized/``, or with ``out_dir`` in ``out_dir/<the product's
    prim name>/`` (products whose files share a name in different folders,
    such as stereo eyes, never meet there); the file name is the source's."""
    src = product.file_for(frame)
    if out_dir is None:
        return src.parent / "harmonized" / src.name
    return out_dir / product.name / src.name


def check_outputs(
    products: list[ProductInfo], frames: list[int], out_dir: Path | None
) -> None:
    """Raises :class:`SettingsError` before any work when two (product, frame)
    would be written to one file, or an output would be one of the inputs
    (of any product and frame)."""
    inputs: dict[Path, tuple[str, int]] = {}
    for p in products:
        for f in frames:
            inputs.setdefault(p.file_for(f).resolve(), (p.path, f))
    outputs: dict[Path, tuple[ProductInfo, int]] = {}
    for p in products:
        for f in frames:
            out = output_path(p, f, out_dir)
            key = out.resolve()
            if key in inputs:
                q, g = inputs[key]
                where = f"render product {p.path} frame {f}"
                if (q, g) == (p.path, f):
                    raise SettingsError(
                        f"{where} ({p.file_for(f)}): the output would overwrite "
                        "the input; choose another --out-dir"
                    )
                raise SettingsError(
                    f"{where}: the output {out} would overwrite the input of "
                    f"render product {q} frame {g}; choose another --out-dir"
                )
            if key in outputs:
                q, g = outputs[key]
                if out_dir is None:
                    hint = (
                        "use --out-dir DIR, which writes each product into "
                        "DIR/<product name>/"
                    )
                elif q.path == p.path:
                    hint = (
                        "the files differ only in their folders; leave out --out-dir "
                        "(outputs go beside each file, in harmonized/)"
                    )
                else:
                    hint = (
                        "products with one prim name share DIR/<product name>/; "
                        "run them separately with different --out-dir"
                    )
                raise SettingsError(
                    f"render products {q.path} frame {g} and {p.path} frame {f} would "
                    f"both be written to {out}; {hint}"
                )
            outputs[key] = (p, f)


class ProductRunner:
    """Runs one product's frames through one session, keeping temporal state."""

    def __init__(
        self,
        product: ProductInfo,
        settings: SettingsInfo,
        device: Any,
        options: Options,
    ) -> None:
        hz = binding.load()
        self.hz = hz
        self.product = product
        self.settings = settings
        self.options = options
        self.roles = map_vars(product, options.user_map)
        params: dict[str, Any] = dict(options.params)
        params["backend"] = options.backend
        for k, v in product.params.items():
            params.setdefault(k, v)
        depth_var = self.roles.get("depth")
        if depth_var is not None and depth_var.depth_kind:
            params.setdefault("depth_kind", depth_var.depth_kind)
        self._fixed_light = self._options_light(options, params)
        #: The ``light_direction`` the session holds, None while the
        #: session holds the user's own (``params``) or nothing set yet.
        self._light_param: str | None = None
        self._distant: list[Any] | None = None
        self._domes: list[Any] | None = None
        #: The ``light_ratio`` the session holds (0.0: unset), and the
        #: stage's DistantLight and DomeLight prims, found once per run.
        self._ratio_param = 0.0
        self._ratio_lights: list[Any] | None = None
        #: The ``light_color`` and ``ambient_color`` the session holds
        #: ("": unset), those the params do not give.
        self._color_params: dict[str, str] = {
            k: "" for k in ("light_color", "ambient_color") if k not in params
        }
        if "light_direction" not in params:
            # The stage's and the CLI's directions are in the stage's world.
            params["light_space"] = "world"
        try:
            self.session = hz.Session(device, **params)
        except hz.HarmonizerError as e:
            raise UsdHarmonizerError(
                f"render product {product.path}: cannot create a session: {e}"
            ) from e
        self.camera = product.camera_prim()
        self._light_prims = [
            p
            for p in (
                product.stage.GetPrimAtPath(product.path),
                settings.stage.GetPrimAtPath(settings.path),
            )
            if p and p.IsValid()
        ]
        self.last_frame: int | None = None
        self.results: list[FrameResult] = []
        self._converters: dict[tuple[Any, ...], ColorConverter] = {}

    @staticmethod
    def _options_light(options: Options, params: dict[str, Any]) -> Light | None:
        """The light every frame gets (``light_direction`` in the params, a
        direction or ``"none"`` in :attr:`Options.light`), or None for the
        stage's light at each frame."""
        if "light_direction" in params:
            text = str(params["light_direction"]).strip()
            d = None
            if text:
                parts = text.replace(",", " ").split()
                d = normalized(parts, f"parameter light_direction {text!r}")
            space = params.get("light_space", "world")
            return Light(d, f"parameter light_direction ({space} space)")
        light = options.light
        if isinstance(light, str):
            if light == "auto":
                return None
            if light == "none":
                return NO_LIGHT
            raise SettingsError(
                f"light {light!r}: expected 'auto', 'none' or a direction (x, y, z)"
            )
        d = normalized(light, "light direction")
        if d is None:
            raise SettingsError(
                "light direction (0, 0, 0): the zero vector has no direction; use 'none'"
            )
        return Light(d, "--light-direction")

    def light_for(self, frame: int) -> Light:
        """The light of ``frame`` (see :attr:`Options.light`)."""
        if self._fixed_light is not None:
            return self._fixed_light
        if self._distant is None:  # the stage's lights, found once per run
            lights = self._stage_lights()
            self._distant = [p for p in lights if not is_dome(p)]
            self._domes = [p for p in lights if is_dome(p)]
        return light_at(self.product.stage, self._light_prims, frame, self._distant, self._domes)

    def _stage_lights(self) -> list[Any]:
        """The stage's DistantLight and DomeLight prims (one traversal per run)."""
        if self._ratio_lights is None:
            self._ratio_lights = ratio_lights(self.product.stage)
        return self._ratio_lights

    def light_ratio_for(self, frame: int, light: Light) -> tuple[float | None, str]:
        """The ``light_ratio`` of ``frame`` and where it came from: the
        params' own (then never changed here), none without a light, else
        the stage's (:func:`usd_harmonizer.light.light_ratio_at`)."""
        got = self.scene_light_for(frame, light)
        return got.ratio, got.source

    def scene_light_for(self, frame: int, light: Light) -> SceneLight:
        """:meth:`light_ratio_for` with the lights' colors
        (:func:`usd_harmonizer.light.scene_light_at`)."""
        if "light_ratio" in self.options.params:
            return SceneLight(None, "parameter light_ratio")
        if light.direction is None:
            return SceneLight(None, "none")
        return scene_light_at(self.product.stage, self._light_prims, frame, self._stage_lights())

    # -- paths ---------------------------------------------------------------
    def output_for(self, frame: int) -> Path:
        """The enhanced file of ``frame`` (see :func:`output_path`)."""
        return output_path(self.product, frame, self.options.out_dir)

    # -- one frame -------------------------------------------------------------
    def _converter(self, attrs: dict[str, Any], file_name: str) -> ColorConverter:
        var = self.roles["color"]
        # Own declarations first (var, product), then inherited ones.
        declared = (
            var.color_space
            or self.product.color_space
            or var.inherited_color_space
            or self.product.inherited_color_space
        )
        key = (
            declared,
            attrs.get("colorInteropID"),
            attrs.get("oiio:ColorSpace"),
            self.settings.rendering_color_space,
        )
        if key not in self._converters:
            self._converters[key] = converter_for(
                declared,
                attrs,
                file_name,
                self.settings.rendering_color_space,
                self.options.ocio_config,
            )
        return self._converters[key]

    def process_frame(
        self,
        frame: int,
        reset: bool = False,
        progress: Callable[[float], bool] | None = None,
        write: bool = True,
    ) -> FrameResult:
        """Enhances ``frame`` and writes its output; returns what happened.
        With ``write`` False (a pre-roll frame) the frame only warms the
        session's temporal state: nothing is written and the result is not
        added to :attr:`results`."""
        prod = self.product
        src = self.product.file_for(frame)
        where = f"render product {prod.path} frame {frame} ({src})"
        out_path = self.output_for(frame)
        if out_path.resolve() == src.resolve():
            raise FrameError(
                f"{where}: the output would overwrite the input; choose another --out-dir"
            )
        t0 = time.perf_counter()
        img = read_exr(src, where)
        t_read = time.perf_counter()
        spec = img.parts[0].spec
        fw, fh = spec.full_width, spec.full_height
        rw, rh = prod.resolution
        if abs(fw / fh - rw / rh) > 2.0 / min(fw, fh):
            raise ProductFileError(
                f"{where}: the file is {fw}x{fh} but the product's resolution is "
                f"{rw}x{rh} (a different aspect ratio)"
            )
        names = img.channel_names
        b: dict[str, Binding] = {
            r: find_channels(r, v, names, where) for r, v in self.roles.items()
        }
        color_b = b["color"]
        rgb = img.stack(color_b.channels)
        cov_channels = [
            c
            for c in (
                b["coverage"].channels[0] if "coverage" in b else None,
                color_b.alpha,
            )
            if c
        ]
        coverage = (
            img.channel(cov_channels[0]).astype(np.float32) if cov_channels else None
        )
        attrs = img.attributes()
        conv = self._converter(attrs, str(src))
        t_c0 = time.perf_counter()
        lin = conv.to_linear(rgb, coverage)
        t_c1 = time.perf_counter()
        kw: dict[str, Any] = {}
        inputs = ["color"]
        if "depth" in b:
            kw["depth"] = empty_depth_to_far(img.channel(b["depth"].channels[0]))
            inputs.append("depth")
        if "motion" in b:
            kw["motion"] = img.stack(b["motion"].channels)
            scale = (
                self.options.motion_scale
                or self.roles["motion"].motion_scale
                or (1.0, 1.0)
            )
            kw["motion_vector_scale"] = scale
            inputs.append("motion")
        if "normal" in b:
            kw["normal"] = img.stack(b["normal"].channels)
            inputs.append("normal")
        if "albedo" in b:
            # Reflectance in the product's color space: same primaries as the color.
            kw["albedo"] = conv.to_linear(img.stack(b["albedo"].channels))
            inputs.append("albedo")
        if "denoise_normal" in b:
            kw["denoise_normal"] = img.stack(b["denoise_normal"].channels)
            inputs.append("denoise_normal")
        if coverage is not None:
            kw["coverage"] = coverage
            inputs.append("coverage")
        if "insert_mask" in b:
            kw["insert_mask"] = np.clip(
                img.channel(b["insert_mask"].channels[0]), 0.0, 1.0
            ).astype(np.float32)
            inputs.append("insert_mask")
        if "insert_id" in b:
            # Integer object ids held as floats: passed as they are (the
            # library counts non-finite ones as 0 and warns).
            kw["insert_id"] = img.channel(b["insert_id"].channels[0]).astype(np.float32)
            inputs.append("insert_id")
        if self.options.always_cameras or "motion" not in b:
            if self.camera is not None:
                w2c, w2n = exr_matrices(
                    self.camera,
                    frame,
                    prod.resolution,
                    prod.pixel_aspect,
                    prod.conform_policy,
                )
            else:
                w2c, w2n = (
                    _header_matrix(attrs, "worldToCamera"),
                    _header_matrix(attrs, "worldToNDC"),
                )
            if w2c is not None and w2n is not None:
                w2n = w2n @ data_window_matrix(spec)
                kw["world_to_camera"] = w2c.astype(np.float32)
                kw["world_to_ndc"] = w2n.astype(np.float32)
                inputs.append("camera")
        hz = self.hz
        light = self.light_for(frame)
        own = "light_direction" in self.options.params
        if not own and light.param != self._light_param:
            # Not a reset: the library keeps the temporal state across it.
            try:
                self.session.set("light_direction", light.param)
                self.session.commit()
            except hz.HarmonizerError as e:
                raise FrameError(
                    f"{where}: light direction from {light.source}: {e}"
                ) from e
            self._light_param = light.param
        scene_light = self.scene_light_for(frame, light)
        ratio, ratio_source = scene_light.ratio, scene_light.source
        # The lights' colors ("": unset), unless the params give their own.
        given = scene_light.params()
        colors = {
            k: given.get(k, "")
            for k in ("light_color", "ambient_color")
            if k not in self.options.params
        }
        if (ratio or 0.0) != self._ratio_param or colors != self._color_params:
            try:
                self.session.set("light_ratio", float(ratio or 0.0))
                for k, v in colors.items():
                    self.session.set(k, v)
                self.session.commit()
            except hz.HarmonizerError as e:
                raise FrameError(f"{where}: light ratio from {ratio_source}: {e}") from e
            self._ratio_param = ratio or 0.0
            self._color_params = colors
        try:
            t_l0 = time.perf_counter()
            out = self.session.process(
                lin, frame_index=frame, reset=reset, progress=progress, **kw
            )
        except hz.HarmonizerError as e:
            raise FrameError(f"{where}: {e}") from e
        report = self.session.last_report or {}
        t_l1 = time.perf_counter()
        reset_reason = report.get("reset")
        backend = str(report.get("backend") or self.session.backend_name)
        # What the frame's result says whether or not it is written.
        common = dict(
            product=prod.path,
            frame=frame,
            source=src,
            output=out_path,
            reset=str(reset_reason) if reset_reason else None,
            backend=backend,
            total_ms=float(report.get("total_ms") or 0.0),
            history_used=int(report.get("history_used") or 0),
            color_space=conv.source_name,
            inputs=inputs,
            warnings=list(report.get("warnings") or []),
            usd_color_space=conv.usd_name,
            denoised=bool(report.get("denoised")),
            denoise_decision=report.get("denoise_decision"),
            noise_level=report.get("noise_level"),
            light_direction=light.direction,
            light_source=light.source,
            light_ratio=ratio,
            light_ratio_source=ratio_source,
        )
        if not write:
            self.last_frame = frame
            return FrameResult(
                **common,
                timings={"read": (t_read - t0) * 1e3, "library": (t_l1 - t_l0) * 1e3},
                preroll=True,
            )
        back = conv.from_linear(
            out[..., :3], out[..., 3] if coverage is not None else None
        )
        for i, c in enumerate(color_b.channels):
            img.set_channel(c, back[..., i])
        for c in cov_channels:
            img.set_channel(c, out[..., 3])
        extra = {
            "harmonizer:version": hz.version(),
            "harmonizer:backend": backend,
            "harmonizer:model": self.session.model_name or "none",
            "harmonizer:frame": int(frame),
            "harmonizer:reset": str(reset_reason) if reset_reason else "none",
            "harmonizer:colorSpace": conv.source_name,
            "harmonizer:product": prod.path,
            "harmonizer:source": os.fspath(src),
            "harmonizer:denoised": bool(report.get("denoised")),
        }
        if light.direction is not None:
            extra["harmonizer:lightDirection"] = light.param
        if ratio is not None:
            extra["harmonizer:lightRatio"] = float(ratio)
        t_w0 = time.perf_counter()
        write_exr_atomic(img, out_path, extra, where)
        t_w1 = time.perf_counter()
        self.last_frame = frame
        result = FrameResult(
            **common,
            timings={
                "read": (t_read - t0) * 1e3,
                "color": (t_c1 - t_c0 + t_w0 - t_l1) * 1e3,
                "library": (t_l1 - t_l0) * 1e3,
                "write": (t_w1 - t_w0) * 1e3,
                "total": (t_w1 - t0) * 1e3,
            },
        )
        self.results.append(result)
        return result

    def close(self) -> None:
        """Releases the session."""
        self.session.close()
