"""Device and Session over the C ABI (ctypes + numpy)."""

from __future__ import annotations

import ctypes
import json
import logging
import os
import threading
from collections.abc import Callable, Sequence
from ctypes import byref, c_bool, c_double, c_int64, c_size_t, c_uint32, c_void_p
from typing import Any, Union

import numpy as np

from . import _native as N
from .errors import CancelledError, InvalidArgumentError, InvalidOperationError, Status

_log = logging.getLogger("harmonizer")

PathLike = Union[str, "os.PathLike[str]"]
ModelSpec = Union[None, PathLike, "tuple[bytes, str]"]
ParamValue = Union[int, float, bool, str]


def version() -> str:
    """The library's version (``hz_version()``)."""
    return N.lib().hz_version().decode()


def parse_param(text: str) -> ParamValue:
    """A session parameter's value from command-line text: ``true``/``on``/
    ``yes`` and ``false``/``off``/``no`` (any case) are booleans, then an
    integer, a number, else the text itself (``"0.4,-0.7,0.6"`` stays a
    string)."""
    low = text.lower()
    if low in ("true", "on", "yes"):
        return True
    if low in ("false", "off", "no"):
        return False
    for conv in (int, float):
        try:
            return conv(text)
        except ValueError:
            pass
    return text


class Device:
    """Thread pool, ONNX Runtime location, memory limit and model; shared by sessions.

    ``ort_library``: ``libonnxruntime``; ``None`` = ``$HARMONIZER_ORT_LIB`` or
    ``$ORT_DYLIB_PATH`` when set, else the installed ``onnxruntime`` wheel's
    (``harmonizer[neural]``), else the library's own search. Open Image Denoise
    (the denoise stage): ``$HARMONIZER_OIDN_LIB`` when set, else the installed
    ``pyoidn`` wheel's (``harmonizer[denoise]``; put into ``HARMONIZER_OIDN_LIB``
    of this process), else the library's own search.

    ``model``: ``None`` = the embedded default, a path to an ``.onnx`` file (its
    JSON manifest beside it), or ``(onnx_bytes, manifest_json_str)``.
    """

    def __init__(
        self,
        threads: int = 0,
        ort_library: PathLike | None = None,
        memory_limit: int = 0,
        model: ModelSpec = None,
    ) -> None:
        lib = N.lib()
        if not isinstance(threads, (int, np.integer)) or isinstance(threads, bool) or not 0 <= threads < 2**32:
            raise InvalidArgumentError(f"Device: threads must be an integer >= 0, got {threads!r}")
        if not isinstance(memory_limit, (int, np.integer)) or not 0 <= memory_limit < 2**64:
            raise InvalidArgumentError(f"Device: memory_limit must be bytes >= 0, got {memory_limit!r}")
        opts = N.hz_device_options()
        opts.struct_size = ctypes.sizeof(N.hz_device_options)
        opts.threads = int(threads)
        opts.memory_limit = int(memory_limit)
        if ort_library is None and not (os.environ.get("HARMONIZER_ORT_LIB") or os.environ.get("ORT_DYLIB_PATH")):
            # pip install harmonizer[neural]: the onnxruntime wheel beside this one.
            ort_library = N.ort_library()
        if ort_library is not None:
            opts.ort_library = os.fsencode(ort_library)
        if not os.environ.get("HARMONIZER_OIDN_LIB"):
            # pip install harmonizer[denoise]: the pyoidn wheel beside this one. The C
            # ABI's device options have no Open Image Denoise path; the library reads
            # this variable (set in this process only, and only when unset).
            oidn = N.oidn_library()
            if oidn is not None:
                os.environ["HARMONIZER_OIDN_LIB"] = str(oidn)
        keep: Any = None
        if model is None:
            pass
        elif isinstance(model, tuple):
            if len(model) != 2 or not isinstance(model[0], (bytes, bytearray, memoryview)) or not isinstance(model[1], str):
                raise InvalidArgumentError("Device: model must be a path or a tuple (onnx_bytes, manifest_json_str)")
            keep = ctypes.create_string_buffer(bytes(model[0]), len(model[0]))
            opts.model_data = ctypes.cast(keep, c_void_p)
            opts.model_data_size = len(model[0])
            opts.model_manifest = model[1].encode("utf-8")
        elif isinstance(model, (str, os.PathLike)):
            opts.model_path = os.fsencode(model)
        else:
            raise InvalidArgumentError(f"Device: model must be None, a path or (onnx_bytes, manifest), got {type(model).__name__}")
        handle = c_void_p()
        N.check(lib.hz_device_new(N.ABI_MAJOR, byref(opts), byref(handle)))
        del keep
        self._handle: int | None = handle.value

    @property
    def handle(self) -> int:
        """The ``hz_device*`` (raises if closed)."""
        if self._handle is None:
            raise InvalidOperationError("Device: the device is closed")
        return self._handle

    @property
    def threads(self) -> int:
        """Worker threads of the device's pool."""
        n = c_uint32()
        N.check(N.lib().hz_device_get_threads(self.handle, byref(n)))
        return n.value

    def close(self) -> None:
        """Releases the device (sessions created on it stay usable). Idempotent."""
        h, self._handle = self._handle, None
        if h is not None:
            N.lib().hz_device_free(h)

    def __enter__(self) -> Device:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # interpreter shutdown
            pass


MessageCallback = Callable[[str, str], None]
ProgressCallback = Callable[[float], bool]


def _default_message(level: str, text: str) -> None:
    _log.log(logging.WARNING if level == "warning" else logging.INFO, "%s", text)


def _array_image(arr: np.ndarray, what: str, writable: bool = False) -> tuple[N.hz_image, np.ndarray]:
    """Describes an (H, W) or (H, W, C) float32/float16 array as an hz_image,
    without copying when its strides allow (returns the array actually used)."""
    if not isinstance(arr, np.ndarray):
        if writable:
            raise InvalidArgumentError(f"{what}: expected a numpy array, got {type(arr).__name__}")
        arr = np.asarray(arr)
    if arr.ndim == 2:
        h, w = arr.shape
        c = 1
    elif arr.ndim == 3:
        h, w, c = arr.shape
    else:
        raise InvalidArgumentError(f"{what}: expected shape (H, W) or (H, W, C), got {arr.shape}")
    if arr.dtype == np.float32:
        fmt = N.HZ_FORMAT_F32
    elif arr.dtype == np.float16:
        fmt = N.HZ_FORMAT_F16
    elif not writable and (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        arr = arr.astype(np.float32)
        fmt = N.HZ_FORMAT_F32
    else:
        raise InvalidArgumentError(f"{what}: dtype {arr.dtype} is not float32 or float16")
    item = arr.itemsize
    st = arr.strides if arr.ndim == 3 else (*arr.strides, item)
    rs, ps, cs = st
    ok = (
        (c == 1 or cs == item)
        and (w == 1 or (ps > 0 and ps % item == 0 and ps >= c * item))
        and (h == 1 or (rs > 0 and rs % item == 0))
    )
    pixel = ps if w > 1 else c * item
    row = rs if h > 1 else w * pixel
    if ok and h > 1 and row < w * pixel:
        ok = False
    if arr.size == 0:
        ok = True  # nothing to read; the library reports the empty size
    if not ok:
        if writable:
            return _array_image(np.empty(arr.shape, arr.dtype), what, True)
        arr = np.ascontiguousarray(arr)
        return _array_image(arr, what)
    img = N.hz_image()
    img.struct_size = ctypes.sizeof(N.hz_image)
    img.format = fmt
    img.channels = c
    img.width = w
    img.height = h
    img.offset = 0
    img.pixel_stride = pixel
    img.row_stride = row
    img.data = arr.ctypes.data if arr.size else None
    return img, arr


def _matrix(m: Any, what: str) -> np.ndarray:
    a = np.ascontiguousarray(np.asarray(m, dtype=np.float32))
    if a.size != 16:
        raise InvalidArgumentError(f"{what}: expected a 4x4 matrix, got shape {a.shape}")
    return a.reshape(16)


class Session:
    """One camera's temporal enhancer. Parameters by name (for example
    ``backend="classical"``, ``context_frames=4``, ``strength=1.0``,
    ``gap_policy="reset"``, ``depth_kind="planar"``) are set and committed.

    ``on_message(level, text)`` (level ``"info"`` or ``"warning"``) receives the
    library's warnings after each frame; the default logs them to
    ``logging.getLogger("harmonizer")``. Calls on one session are serialized;
    different sessions may be used from different threads.
    """

    def __init__(self, device: Device, *, on_message: MessageCallback | None = None, **params: ParamValue) -> None:
        if not isinstance(device, Device):
            raise InvalidArgumentError(f"Session: device must be a harmonizer.Device, got {type(device).__name__}")
        self._lib = N.lib()
        self._device = device
        self._lock = threading.RLock()
        self._report: dict[str, Any] | None = None
        handle = c_void_p()
        N.check(self._lib.hz_session_new(device.handle, byref(handle)))
        self._handle: int | None = handle.value
        self._on_message = on_message or _default_message
        self._message_exc: BaseException | None = None

        def message(_user: int | None, level: int, text: bytes) -> None:
            lvl = "warning" if level == N.HZ_MESSAGE_WARNING else "info"
            try:
                self._on_message(lvl, text.decode("utf-8", "replace"))
            except BaseException as e:  # noqa: BLE001 (re-raised after the call)
                self._message_exc = e

        self._message_cb = N.MESSAGE_FN(message)
        try:
            N.check(self._lib.hz_session_set_message_callback(self._handle, self._message_cb, None))
            for name, value in params.items():
                self.set(name, value)
            self.commit()
        except BaseException:
            self.close()
            raise

    @property
    def handle(self) -> int:
        """The ``hz_session*`` (raises if closed)."""
        if self._handle is None:
            raise InvalidOperationError("Session: the session is closed")
        return self._handle

    # -- parameters -------------------------------------------------------
    def set(self, name: str, value: ParamValue) -> None:
        """Stages a parameter; it takes effect at :meth:`commit`."""
        key = name.encode()
        with self._lock:
            h = self.handle
            if isinstance(value, (bool, np.bool_)):
                N.check(self._lib.hz_session_set_bool(h, key, bool(value)))
            elif isinstance(value, (int, np.integer)):
                if not -(2**63) <= int(value) < 2**63:
                    raise InvalidArgumentError(f"parameter {name!r}: {value} does not fit in 64 bits")
                N.check(self._lib.hz_session_set_int(h, key, int(value)))
            elif isinstance(value, (float, np.floating)):
                N.check(self._lib.hz_session_set_float(h, key, float(value)))
            elif isinstance(value, (str, os.PathLike)):
                N.check(self._lib.hz_session_set_string(h, key, os.fsdecode(value).encode("utf-8")))
            else:
                raise InvalidArgumentError(
                    f"parameter {name!r}: value {value!r} of type {type(value).__name__} is not int, float, bool or str"
                )

    def get(self, name: str) -> ParamValue:
        """Reads a (staged) parameter."""
        key = name.encode()
        with self._lock:
            h = self.handle
            t = c_uint32()
            N.check(self._lib.hz_session_get_type(h, key, byref(t)))
            if t.value == N.HZ_PARAM_INT:
                i = c_int64()
                N.check(self._lib.hz_session_get_int(h, key, byref(i)))
                return i.value
            if t.value == N.HZ_PARAM_FLOAT:
                f = c_double()
                N.check(self._lib.hz_session_get_float(h, key, byref(f)))
                return f.value
            if t.value == N.HZ_PARAM_BOOL:
                b = c_bool()
                N.check(self._lib.hz_session_get_bool(h, key, byref(b)))
                return b.value
            return N.get_string(self._lib.hz_session_get_string, h, key)

    def commit(self) -> None:
        """Applies staged parameters (a backend/context/depth-kind change resets the state)."""
        with self._lock:
            N.check(self._lib.hz_session_commit(self.handle))

    def reset(self) -> None:
        """Drops the temporal state; the next frame is a cold start."""
        with self._lock:
            N.check(self._lib.hz_session_reset(self.handle))

    # -- processing -------------------------------------------------------
    def process(
        self,
        color: np.ndarray,
        *,
        depth: np.ndarray | None = None,
        motion: np.ndarray | None = None,
        normal: np.ndarray | None = None,
        albedo: np.ndarray | None = None,
        denoise_normal: np.ndarray | None = None,
        coverage: np.ndarray | None = None,
        insert_mask: np.ndarray | None = None,
        insert_id: np.ndarray | None = None,
        world_to_camera: Any = None,
        world_to_ndc: Any = None,
        frame_index: int | None = None,
        reset: bool = False,
        motion_vector_scale: tuple[float, float] = (1.0, 1.0),
        out: np.ndarray | None = None,
        progress: ProgressCallback | None = None,
    ) -> np.ndarray:
        """Enhances one frame.

        ``color``: float32/float16 (H, W, C), C >= 3, RGB premultiplied by
        coverage, scene-linear Linear Rec.709 (a 4th channel is ignored). Any
        strides: float32/float16 arrays with positive strides are read in place.
        ``depth``/``coverage``/``insert_mask``: (H, W) or (H, W, 1); ``motion``:
        (H, W, 2) pixels, current to previous frame, x right, y down (after
        ``motion_vector_scale``); ``normal``: (H, W, 3). ``albedo``: (H, W, 3)
        linear RGB reflectance in [0, 1] (Cycles' Denoising Albedo or any
        renderer's albedo AOV) and ``denoise_normal``: (H, W, 3) the
        denoiser's normals, any space (Cycles' Denoising Normal; when absent
        the denoiser uses ``normal``), read only by the denoise stage
        (parameter ``denoise``) and validated as ``normal`` is.
        ``insert_id``: (H, W) or (H, W, 1) integer object ids as floats (0:
        not an inserted object, for example Blender's Object Index pass):
        each distinct id above 0 among the insert's pixels is one object,
        harmonized with its own filter and followed over time by its id;
        without ``insert_mask`` the mask is 1 where the id is above 0.
        ``world_to_camera`` / ``world_to_ndc``: 4x4 OpenEXR row-vector
        matrices.
        ``out``: float32/float16 (H, W, 3|4) to write into (may be ``color``
        itself: in place); when ``None`` a new (H, W, 4) RGBA float32 array is
        returned. ``progress(p) -> bool``: returning False cancels
        (:class:`CancelledError`, state unchanged). Returns the output array.
        """
        keep: list[Any] = []
        cimg, carr = _array_image(color, "color")
        keep.append(carr)
        if carr.ndim != 3:
            raise InvalidArgumentError(f"color: expected shape (H, W, C) with C >= 3, got {np.shape(color)}")
        frame = N.hz_frame()
        frame.struct_size = ctypes.sizeof(N.hz_frame)
        frame.color = ctypes.pointer(cimg)
        for name, arr in (
            ("depth", depth),
            ("motion", motion),
            ("normal", normal),
            ("albedo", albedo),
            ("denoise_normal", denoise_normal),
            ("coverage", coverage),
            ("insert_mask", insert_mask),
            ("insert_id", insert_id),
        ):
            if arr is not None:
                img, a = _array_image(arr, name)
                keep += [img, a]
                setattr(frame, name, ctypes.pointer(img))
        if (world_to_camera is None) != (world_to_ndc is None):
            raise InvalidArgumentError("world_to_camera and world_to_ndc must be given together")
        if world_to_camera is not None:
            w2c, w2n = _matrix(world_to_camera, "world_to_camera"), _matrix(world_to_ndc, "world_to_ndc")
            keep += [w2c, w2n]
            frame.world_to_camera = w2c.ctypes.data_as(ctypes.POINTER(ctypes.c_float))
            frame.world_to_ndc = w2n.ctypes.data_as(ctypes.POINTER(ctypes.c_float))
        flags = N.HZ_FRAME_RESET if reset else 0
        if frame_index is not None:
            frame.frame_index = int(frame_index)
            flags |= N.HZ_FRAME_HAS_INDEX
        frame.flags = flags
        sx, sy = motion_vector_scale
        frame.motion_vector_scale[0] = float(sx)
        frame.motion_vector_scale[1] = float(sy)
        if float(sx) == 0.0 and float(sy) == 0.0:
            raise InvalidArgumentError("motion_vector_scale (0, 0) would erase the motion vectors; omit motion instead")

        h, w = carr.shape[:2]
        if out is None:
            result = np.empty((h, w, 4), np.float32)
        else:
            if not isinstance(out, np.ndarray) or out.ndim != 3 or out.shape[:2] != (h, w) or out.shape[2] not in (3, 4):
                raise InvalidArgumentError(f"out: expected shape ({h}, {w}, 3|4), got {np.shape(out)}")
            if not out.flags.writeable:
                raise InvalidArgumentError("out: the array is read-only")
            result = out
        oimg, oarr = _array_image(result, "output", writable=True)

        progress_exc: list[BaseException] = []
        with self._lock:
            handle = self.handle
            pcb = None
            if progress is not None:

                def on_progress(_user: int | None, p: float) -> bool:
                    try:
                        return bool(progress(p))
                    except BaseException as e:  # noqa: BLE001 (re-raised after the call)
                        progress_exc.append(e)
                        return False

                pcb = N.PROGRESS_FN(on_progress)
                N.check(self._lib.hz_session_set_progress_callback(handle, pcb, None))
            self._message_exc = None
            try:
                status = self._lib.hz_session_process(handle, byref(frame), byref(oimg))
            finally:
                if pcb is not None:
                    self._lib.hz_session_set_progress_callback(handle, N.PROGRESS_FN(), None)
            if progress_exc:
                raise CancelledError(
                    f"hz_session_process: the progress callback raised {progress_exc[0]!r}", Status.CANCELLED
                ) from progress_exc[0]
            N.check(status)
            self._report = None
            if self._message_exc is not None:
                exc, self._message_exc = self._message_exc, None
                raise exc
        del keep
        if oarr is not result:
            np.copyto(result, oarr)
        return result

    def run_sequence(
        self,
        input: PathLike,
        output: PathLike,
        *,
        frames: tuple[int, int] | str | None = None,
        preroll: int = 0,
        layout: str = "auto",
        channels: list[str] | None = None,
        insert_index: int | Sequence[int] | None = None,
        render_hints: bool = False,
        report: PathLike | None = None,
        on_frame: Callable[[dict[str, Any]], bool | None] | None = None,
    ) -> list[dict[str, Any]]:
        """Runs this session over an EXR sequence on disk, read and written
        by the library itself (``hz_run_sequence``): what ``harmonize run
        INPUT -o OUTPUT --frames A-B --preroll N`` does with this session's
        parameters, byte for byte.

        ``input``/``output``: frame patterns (``####``, ``%04d``, ``$F4``,
        ``${F4}``, ``<F4>``). ``frames``: ``(A, B)`` or ``"A-B"``, the frames
        written (all must exist; default every existing frame). ``preroll``:
        the frames before A processed first and not written, so a chunk
        starts with the temporal state of a sequential run (needs
        ``frames``). ``layout``: ``auto``, ``generic`` or ``blender``;
        ``channels``: ``harmonize run --channel`` entries (``"color=R,G,B"``);
        ``insert_index``: the Blender layout's Object Index of the insert,
        or a sequence of several (each then an object of its own, harmonized
        by its index; above 0, each named once), as ``harmonize run
        --insert-index 3,5``.
        ``render_hints``: when this session's ``denoise`` and ``samples``
        are the defaults, take what the first file's headers say (as
        ``harmonize run`` does). ``report``: a JSON report file (the CLI's
        ``--report``). ``on_frame(frame_report)`` sees each frame (pre-roll
        frames too, ``"preroll": True``); returning False stops the run
        (:class:`CancelledError`). Outputs are written atomically (a
        temporary file renamed): complete or absent. On an error the frames
        before it stay written. Returns every frame's report (dicts).
        """
        fn = N.optional("hz_run_sequence")
        opts = N.hz_run_options()
        opts.struct_size = ctypes.sizeof(N.hz_run_options)
        opts.input = os.fsencode(input)
        opts.output = os.fsencode(output)
        opts.layout = layout.encode("utf-8")
        if channels:
            opts.channels = ";".join(channels).encode("utf-8")
        flags = 0
        if frames is not None:
            if isinstance(frames, str):
                a, sep, b = frames.partition("-")
                try:
                    first, last = int(a), int(b) if sep else int(a)
                except ValueError:
                    raise InvalidArgumentError(f"run_sequence: frames {frames!r} is not A-B") from None
            else:
                first, last = (int(x) for x in frames)
            opts.frame_first, opts.frame_last = first, last
            flags |= N.HZ_RUN_HAS_FRAMES
        if not isinstance(preroll, (int, np.integer)) or isinstance(preroll, bool) or preroll < 0:
            raise InvalidArgumentError(f"run_sequence: preroll must be an integer >= 0, got {preroll!r}")
        opts.preroll = int(preroll)
        keep_indices = None
        if isinstance(insert_index, (list, tuple, np.ndarray)):
            values = [int(v) for v in insert_index]
            if len(values) == 1:
                insert_index = values[0]
            elif values:
                keep_indices = (ctypes.c_int64 * len(values))(*values)
                opts.insert_indices = ctypes.cast(keep_indices, ctypes.POINTER(ctypes.c_int64))
                opts.insert_index_count = len(values)
                insert_index = None
            else:
                insert_index = None
        if insert_index is not None:
            opts.insert_index = int(insert_index)
            flags |= N.HZ_RUN_HAS_INSERT_INDEX
        if render_hints:
            flags |= N.HZ_RUN_RENDER_HINTS
        opts.flags = flags
        if report is not None:
            opts.report = os.fsencode(report)
        seen: list[dict[str, Any]] = []
        raised: list[BaseException] = []

        def frame_cb(_user: int | None, text: bytes) -> bool:
            r = json.loads(text.decode("utf-8"))
            seen.append(r)
            if on_frame is None:
                return True
            try:
                return on_frame(r) is not False
            except BaseException as e:  # noqa: BLE001 (re-raised after the call)
                raised.append(e)
                return False

        cb = N.RUN_FRAME_FN(frame_cb)
        with self._lock:
            status = fn(self.handle, byref(opts), cb, None)
            self._report = None
        if raised:
            raise raised[0]
        N.check(status)
        return seen

    # -- queries ----------------------------------------------------------
    @property
    def last_report(self) -> dict[str, Any] | None:
        """The last successful frame's report, or None before the first frame:
        ``{"frame_index", "reset", "backend", "history_used", "sanitized",
        "out_of_gamut", "denoised", "denoise_decision", "noise_level",
        "warnings", "stages", "total_ms"}``. ``denoised``: whether the denoise
        stage ran on the frame; ``denoise_decision`` (what ``denoise`` decided
        for the sequence and why) and ``noise_level`` (the noise estimate
        ``denoise auto`` measured) are None except on the deciding frame."""
        with self._lock:
            if self._report is None:
                n = c_size_t(0)
                st = self._lib.hz_session_get_report_json(self.handle, None, 0, byref(n))
                if st == 2:  # no frame yet
                    return None
                N.check(st)
                self._report = json.loads(N.get_string(self._lib.hz_session_get_report_json, self.handle))
            return json.loads(json.dumps(self._report))

    def _size(self, fn: Any) -> int:
        n = c_size_t()
        with self._lock:
            N.check(fn(self.handle, byref(n)))
        return n.value

    @property
    def history_length(self) -> int:
        """History frames held."""
        return self._size(self._lib.hz_session_get_history_length)

    @property
    def memory_bytes(self) -> int:
        """Bytes of temporal state held."""
        return self._size(self._lib.hz_session_get_memory_bytes)

    @property
    def tile_overlap(self) -> int:
        """Neural tile overlap in pixels (0 = the model manifest's)."""
        return self._size(self._lib.hz_session_get_tile_overlap)

    @property
    def backend_name(self) -> str:
        """The backend that runs: ``"neural"``, ``"classical"`` or ``"bypass"``."""
        with self._lock:
            return N.get_string(self._lib.hz_session_get_backend_name, self.handle)

    @property
    def model_name(self) -> str | None:
        """The neural model's name, None when the backend is not neural."""
        with self._lock:
            return N.get_string(self._lib.hz_session_get_model_name, self.handle) or None

    @property
    def model_version(self) -> str | None:
        """The neural model's version, None when the backend is not neural."""
        with self._lock:
            return N.get_string(self._lib.hz_session_get_model_version, self.handle) or None

    # -- lifetime ---------------------------------------------------------
    def close(self) -> None:
        """Frees the session. Idempotent."""
        with self._lock:
            h, self._handle = self._handle, None
            if h is not None:
                self._lib.hz_session_free(h)

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass

    def __repr__(self) -> str:
        if self._handle is None:
            return "<harmonizer.Session closed>"
        return f"<harmonizer.Session backend={self.backend_name!r} history={self.history_length}>"

