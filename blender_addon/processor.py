"""One frame through harmonizer: Blender multilayer EXR in, enhanced EXR out.

``FrameProcessor`` reads every part of a raw multilayer EXR, gathers the passes
of one view layer (Combined, Depth, Vector, Normal, Object Index, Cryptomatte,
and Denoising Albedo / Denoising Normal for the denoise stage), converts color
(and the albedo) from the file's scene-linear space to Linear Rec.709, runs the
harmonizer session, converts back and writes a copy of the file with the view
layer's Combined pass replaced, every other part and channel kept.

Nothing here imports ``bpy``: the render handlers and the batch operator both
drive it with plain values.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass, field

import numpy as np

from . import colorspace, exrio

#: Empty depth (sky, holes), as the library expects.
EMPTY_DEPTH = 1.0e10


class FrameError(Exception):
    """A frame could not be enhanced; the message names the file and frame."""


@dataclass
class Options:
    """What to read from the raw file and how (plain values, no ``bpy``)."""

    view_layer: str = "ViewLayer"
    #: 'ALPHA': the Combined alpha is the coverage; 'FULL': every pixel is data.
    coverage: str = "ALPHA"
    #: 'NONE', 'OBJECT_INDEX', 'CRYPTOMATTE' (objects, collections and
    #: Cryptomatte names all resolve to Cryptomatte names).
    mask_source: str = "NONE"
    mask_index: int = 0
    #: Several pass indices (``mask_index`` among them): each index is one
    #: object, its value the object's id. Empty: ``mask_index`` alone.
    mask_indices: list[int] = field(default_factory=list)
    mask_names: list[str] = field(default_factory=list)
    #: Cryptomatte layer: 'CryptoObject', 'CryptoMaterial' or 'CryptoAsset'.
    mask_crypto_layer: str = "CryptoObject"
    #: The space color is in when the file does not say (``colorInteropID``).
    working_space: str = "Linear Rec.709"
    #: Where the enhanced Combined goes: this view layer's pass (always), and
    #: also the composite part when the file has one and this is True.
    replace_composite: bool = False


def cryptomatte_hash(name: str) -> float:
    """The Cryptomatte float id of ``name`` (MurmurHash3_32, seed 0, as the spec says)."""
    data = name.encode("utf-8")
    c1, c2 = 0xCC9E2D51, 0x1B873593
    h = 0
    n = len(data) // 4
    for i in range(n):
        k = struct.unpack_from("<I", data, 4 * i)[0]
        k = (k * c1) & 0xFFFFFFFF
        k = ((k << 15) | (k >> 17)) & 0xFFFFFFFF
        k = (k * c2) & 0xFFFFFFFF
        h ^= k
        h = ((h << 13) | (h >> 19)) & 0xFFFFFFFF
        h = (h * 5 + 0xE6546B64) & 0xFFFFFFFF
    tail = data[4 * n :]
    k = 0
    if len(tail) >= 3:
        k ^= tail[2] << 16
    if len(tail) >= 2:
        k ^= tail[1] << 8
    if len(tail) >= 1:
        k ^= tail[0]
        k = (k * c1) & 0xFFFFFFFF
        k = ((k << 15) | (k >> 17)) & 0xFFFFFFFF
        k = (k * c2) & 0xFFFFFFFF
        h ^= k
    h ^= len(data)
    h ^= h >> 16
    h = (h * 0x85EBCA6B) & 0xFFFFFFFF
    h ^= h >> 13
    h = (h * 0xC2B2AE35) & 0xFFFFFFFF
    h ^= h >> 16
    # Keep the float finite and normal: flip the lowest exponent bit for 0 and 255.
    exponent = (h >> 23) & 0xFF
    if exponent in (0, 255):
        h ^= 1 << 23
    return struct.unpack("<f", struct.pack("<I", h))[0]


def _cryptomatte_ids(exr: exrio.MultiPartExr, layer_name: str, names: list[str]) -> list[float]:
    """Float ids for ``names``: from the file's manifest when it lists them, else hashed."""
    import json

    manifest = {}
    for part in exr.parts:
        for attr in part.spec.extra_attribs:
            if attr.name.startswith("cryptomatte/") and attr.name.endswith("/name") and str(attr.value) == layer_name:
                key = attr.name[len("cryptomatte/") : -len("/name")]
                raw = exr.attribute(f"cryptomatte/{key}/manifest")
                if raw:
                    try:
                        manifest = json.loads(str(raw))
                    except ValueError:
                        manifest = {}
        if manifest:
            break
    ids = []
    for n in names:
        if n in manifest:
            ids.append(struct.unpack("<f", struct.pack("<I", int(manifest[n], 16)))[0])
        else:
            ids.append(cryptomatte_hash(n))
    return ids


def insert_mask(exr: exrio.MultiPartExr, opts: Options, frame: int) -> np.ndarray | None:
    """The insert mask (H, W) in [0, 1] from the configured source, or None."""
    return insert_mask_and_ids(exr, opts, frame)[0]


def insert_mask_and_ids(
    exr: exrio.MultiPartExr, opts: Options, frame: int
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The insert mask (H, W) in [0, 1] from the configured source and the
    inserted objects' ids (H, W), float32, 0 where none; either may be None.

    Several pass indices: each index is one object, its value its id. One
    index: no ids (the library cuts the mask into connected objects).
    Cryptomatte: each matched name is one object, its id its place in the
    list plus 1, a pixel's id the name that covers most of it.
    """
    layer = opts.view_layer
    if opts.mask_source == "NONE":
        return None, None
    if opts.mask_source == "OBJECT_INDEX":
        name = f"{layer}.Object Index.X"
        if not exr.has(name):
            raise FrameError(
                f"{exr.path}: frame {frame}: insert mask from Object Index needs channel {name!r}; "
                "enable the Object Index pass"
            )
        index = np.rint(exr.channel(name))
        if not opts.mask_indices:
            return (index == opts.mask_index).astype(np.float32), None
        ids = np.where(np.isin(index, opts.mask_indices), index, 0.0).astype(np.float32)
        return (ids > 0).astype(np.float32), ids
    if opts.mask_source == "CRYPTOMATTE":
        if not opts.mask_names:
            return None, None
        base = f"{layer}.{opts.mask_crypto_layer}"
        ranks = []
        k = 0
        while exr.has(f"{base}{k:02d}.r"):
            ranks.append(exr.channels([f"{base}{k:02d}.{c}" for c in "rgba"]))
            k += 1
        if not ranks:
            raise FrameError(
                f"{exr.path}: frame {frame}: insert mask from Cryptomatte needs channels {base}00.r/g/b/a; "
                "enable the Cryptomatte pass"
            )
        ids = np.array(_cryptomatte_ids(exr, f"{layer}.{opts.mask_crypto_layer}", opts.mask_names), dtype=np.float32)
        mask = np.zeros((exr.height, exr.width), dtype=np.float32)
        # Each name's coverage of each pixel, summed over the ranks.
        per_name = np.zeros((len(ids), exr.height, exr.width), dtype=np.float32)
        for rank in ranks:
            for id_ch, cov_ch in ((0, 1), (2, 3)):
                hit = np.isin(rank[:, :, id_ch], ids)
                mask += np.where(hit, rank[:, :, cov_ch], 0.0)
                for k, matte in enumerate(ids):
                    per_name[k] += np.where(rank[:, :, id_ch] == matte, rank[:, :, cov_ch], 0.0)
        mask = np.clip(mask, 0.0, 1.0)
        best = per_name.argmax(axis=0)
        object_ids = np.where(per_name.max(axis=0) > 0.0, best + 1, 0).astype(np.float32)
        return mask, object_ids
    raise FrameError(f"insert mask source {opts.mask_source!r} is not one of NONE, OBJECT_INDEX, CRYPTOMATTE")


#: Cycles' Denoising Data passes: (pass, channel suffixes, keyword of ``Session.process``).
DENOISE_PASSES = (
    ("Denoising Albedo", "RGB", "albedo"),
    ("Denoising Normal", "XYZ", "denoise_normal"),
)


def denoise_guides(exr: exrio.MultiPartExr, layer: str, conv, path: str, frame: int) -> dict[str, np.ndarray]:
    """The denoiser's guides from the Denoising Data passes, as ``Session.process`` keywords.

    ``albedo`` is reflectance in the file's color space, converted to Linear
    Rec.709 like the color; ``denoise_normal`` is Cycles' camera-space normal,
    passed as it is (it never replaces the world-space Normal pass). A pass
    with only some of its channels is an error naming the file and channel.
    """
    out: dict[str, np.ndarray] = {}
    for name, comps, key in DENOISE_PASSES:
        names = [f"{layer}.{name}.{c}" for c in comps]
        present = [n for n in names if exr.has(n)]
        if not present:
            continue
        if len(present) != len(names):
            missing = ", ".join(n for n in names if n not in present)
            raise FrameError(
                f"{path}: frame {frame}: the {name} pass lacks channel {missing} (has {', '.join(present)})"
            )
        values = np.array(exr.channels(names), dtype=np.float32, copy=True)
        if key == "albedo":
            conv.to_library(values)
        out[key] = values
    return out


def detect_view_layer(exr: exrio.MultiPartExr) -> str | None:
    """The first view layer with a Combined pass in the file (the Composite part excluded)."""
    for name in exr.channel_names():
        if name.endswith(".Combined.R") and name.count(".") == 2:
            layer = name.split(".")[0]
            if layer != "Composite":
                return layer
    return None


@dataclass
class CameraParams:
    """A Blender perspective camera and the render size, as plain values."""

    matrix_world: np.ndarray  # 4x4, column-vector (Blender's Object.matrix_world)
    lens: float  # mm
    sensor_width: float  # mm
    sensor_height: float  # mm
    sensor_fit: str  # 'AUTO', 'HORIZONTAL' or 'VERTICAL'
    shift_x: float
    shift_y: float
    clip_start: float
    width: int  # pixels
    height: int
    pixel_aspect_x: float = 1.0
    pixel_aspect_y: float = 1.0


def blender_camera_matrices(cam: CameraParams) -> tuple[np.ndarray, np.ndarray]:
    """OpenEXR ``worldToCamera`` and ``worldToNDC`` (row-vector) of a Blender perspective camera.

    Follows Blender's view plane (sensor fit, shift, pixel aspect). Blender
    cameras look down -z; OpenEXR camera space looks down +z, and its NDC runs
    (0,0) top-left to (1,1) bottom-right after dividing by w (= camera z).
    """
    winx, winy = float(cam.width), float(cam.height)
    ycor = cam.pixel_aspect_y / cam.pixel_aspect_x
    fit = cam.sensor_fit
    if fit == "AUTO":
        sensor = cam.sensor_width
        fit = "HORIZONTAL" if cam.pixel_aspect_x * winx >= cam.pixel_aspect_y * winy else "VERTICAL"
    else:
        sensor = cam.sensor_width if fit == "HORIZONTAL" else cam.sensor_height
    viewfac = winx if fit == "HORIZONTAL" else ycor * winy
    f = cam.lens * viewfac / sensor  # pixels per unit of x/z (horizontal pixel units)
    dx, dy = cam.shift_x * viewfac, cam.shift_y * viewfac
    # u = 0.5 + (f x/z - dx) / winx ; v = 0.5 - (f y/z - dy) / (ycor winy)
    cam_to_ndc = np.array(
        [
            [f / winx, 0.0, 0.5 - dx / winx, 0.0],
            [0.0, -f / (ycor * winy), 0.5 + dy / (ycor * winy), 0.0],
            [0.0, 0.0, 1.0, -cam.clip_start],
            [0.0, 0.0, 1.0, 0.0],
        ]
    )
    view_gl = np.linalg.inv(np.asarray(cam.matrix_world, dtype=np.float64))
    world_to_camera = np.diag([1.0, 1.0, -1.0, 1.0]) @ view_gl
    world_to_ndc = cam_to_ndc @ world_to_camera
    return (
        np.ascontiguousarray(world_to_camera.T, dtype=np.float32),
        np.ascontiguousarray(world_to_ndc.T, dtype=np.float32),
    )


def _header_matrix(exr: exrio.MultiPartExr, *names: str) -> np.ndarray | None:
    for n in names:
        v = exr.attribute(n)
        if v is not None:
            try:
                m = np.asarray(v, dtype=np.float32).reshape(4, 4)
            except (ValueError, TypeError):
                continue
            return np.ascontiguousarray(m)
    return None


@dataclass
class FrameResult:
    """What happened to one frame."""

    frame: int
    raw_path: str
    output_path: str
    report: dict
    #: The inputs passed to the library besides color ("depth", "albedo", ...).
    inputs: list = field(default_factory=list)
    #: The session's ``light_direction`` for this frame, read back from the
    #: library (world space, toward the light), or None.
    light_direction: tuple | None = None


class FrameProcessor:
    """Enhances frames of one sequence with one harmonizer session (temporal state).

    ``session`` is a ``harmonizer.Session``; ``ocio`` and ``oiio`` are the
    PyOpenColorIO and OpenImageIO modules; ``ocio_config`` the OCIO config path.
    """

    def __init__(self, session, *, oiio, ocio, ocio_config: str, options: Options):
        self.session = session
        self.oiio = oiio
        self.ocio = ocio
        self.ocio_config = ocio_config
        self.options = options
        self._converters: dict[str, colorspace.Converter] = {}
        #: The ``light_direction`` parameter the session holds.
        self._light_param = ""

    def converter(self, space: str) -> colorspace.Converter:
        """The (cached) converter for ``space``."""
        conv = self._converters.get(space)
        if conv is None:
            conv = colorspace.Converter(self.ocio, self.ocio_config, space)
            self._converters[space] = conv
        return conv

    def file_space(self, exr: exrio.MultiPartExr) -> str:
        """The file's color space: its ``colorInteropID`` if known to the config, else the working space."""
        conv = self.converter(self.options.working_space)
        interop = exr.attribute("colorInteropID")
        return colorspace.file_space(interop, conv.config, self.options.working_space)

    def process(
        self,
        raw_path: str,
        output_path: str,
        *,
        frame: int,
        frame_index: int | None = None,
        camera: tuple[np.ndarray, np.ndarray] | None = None,
        progress=None,
        allow_overwrite: bool = False,
        light_direction: tuple[float, float, float] | None = None,
    ) -> FrameResult:
        """Enhance the frame in ``raw_path`` and write it to ``output_path``.

        ``light_direction``: toward the scene's dominant light, world space
        (the session's ``light_direction``, for inserts' cast shadows), or
        None for none; changing it between frames keeps the temporal state.

        Raises FrameError (or the binding's HarmonizerError) on failure; nothing
        is written then. The raw file is read whole before anything is written,
        so ``allow_overwrite`` may replace it atomically.
        """
        if not allow_overwrite and os.path.abspath(raw_path) == os.path.abspath(output_path):
            raise FrameError(f"{raw_path}: frame {frame}: the enhanced frame would overwrite the raw render")
        try:
            exr = exrio.read(self.oiio, raw_path)
        except exrio.ExrError as exc:
            raise FrameError(f"frame {frame}: {exc}") from exc
        opts = self.options
        layer = opts.view_layer
        rgba_names = [f"{layer}.Combined.{c}" for c in "RGBA"]
        missing = [n for n in rgba_names[:3] if not exr.has(n)]
        if missing:
            layers = sorted({c.split(".")[0] for c in exr.channel_names() if c.count(".") >= 2})
            raise FrameError(
                f"{raw_path}: frame {frame}: view layer {layer!r} has no Combined pass "
                f"(missing {', '.join(missing)}; view layers in the file: {', '.join(layers) or 'none'})"
            )
        has_alpha = exr.has(rgba_names[3])
        names = rgba_names if has_alpha else rgba_names[:3]
        space = self.file_space(exr)
        conv = self.converter(space)

        color = np.array(exr.channels(names), dtype=np.float32, copy=True)
        conv.to_library(color)

        kwargs = {}
        if opts.coverage == "ALPHA" and has_alpha:
            kwargs["coverage"] = color[:, :, 3]
        if exr.has(f"{layer}.Depth.Z"):
            depth = exr.channel(f"{layer}.Depth.Z")
            # Blender writes a huge value for empty pixels; keep it finite and large.
            depth = np.where(np.isfinite(depth) & (depth < EMPTY_DEPTH), depth, EMPTY_DEPTH).astype(np.float32)
            kwargs["depth"] = depth
        if exr.has(f"{layer}.Vector.X") and exr.has(f"{layer}.Vector.Y"):
            kwargs["motion"] = exr.channels([f"{layer}.Vector.X", f"{layer}.Vector.Y"])
            # Blender's Vector pass is +y up; the library's motion is +y down.
            kwargs["motion_vector_scale"] = (1.0, -1.0)
        if all(exr.has(f"{layer}.Normal.{c}") for c in "XYZ"):
            kwargs["normal"] = exr.channels([f"{layer}.Normal.{c}" for c in "XYZ"])
        kwargs.update(denoise_guides(exr, layer, conv, raw_path, frame))
        mask, ids = insert_mask_and_ids(exr, opts, frame)
        if mask is not None:
            kwargs["insert_mask"] = mask
        if ids is not None:
            kwargs["insert_id"] = ids
        if camera is None:
            w2c = _header_matrix(exr, "worldToCamera", "worldtocamera")
            w2n = _header_matrix(exr, "worldToNDC", "worldtondc", "worldtoscreen")
            if w2c is not None and w2n is not None:
                camera = (w2c, w2n)
        if camera is not None:
            kwargs["world_to_camera"], kwargs["world_to_ndc"] = camera
        if progress is not None:
            kwargs["progress"] = progress
        self._set_light(light_direction)

        out = self.session.process(color, frame_index=frame if frame_index is None else frame_index, **kwargs)
        out = np.array(out, dtype=np.float32, copy=True)
        conv.from_library(out)
        report = dict(self.session.last_report or {})
        inputs = [k for k in kwargs if k not in ("progress", "motion_vector_scale", "world_to_ndc")]
        inputs = ["camera" if k == "world_to_camera" else k for k in inputs]

        exr.set_channels(names, out[:, :, : len(names)])
        if opts.replace_composite:
            comp = [f"Composite.Combined.{c}" for c in "RGBA"]
            if all(exr.has(n) for n in comp[:3]):
                exr.set_channels(comp[: len(names)], out[:, :, : len(names)])
        attrs = {
            "harmonizer/frame": str(frame),
            "harmonizer/reset": str(report.get("reset") or "none"),
            "harmonizer/backend": str(report.get("backend", "")),
            "harmonizer/history_used": str(report.get("history_used", "")),
            "harmonizer/source": os.path.basename(raw_path),
            "harmonizer/colorspace": space,
            "harmonizer/denoised": "1" if report.get("denoised") else "0",
        }
        light = self.session.get("light_direction")
        if light:
            attrs["harmonizer/lightDirection"] = light
        try:
            exrio.write(self.oiio, exr, output_path, extra_attributes=attrs)
        except exrio.ExrError as exc:
            raise FrameError(f"frame {frame}: {exc}") from exc
        return FrameResult(
            frame,
            raw_path,
            output_path,
            report,
            inputs,
            tuple(float(c) for c in light.split(",")) if light else None,
        )

    def _set_light(self, direction: tuple[float, float, float] | None) -> None:
        """Stage and commit ``light_direction`` when it changed (world space)."""
        param = "" if direction is None else ", ".join(repr(float(c)) for c in direction)
        if param != self._light_param:
            self.session.set("light_direction", param)
            self.session.commit()
            self._light_param = param
