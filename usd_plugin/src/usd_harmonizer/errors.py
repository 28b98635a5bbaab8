"""Errors of the USD hook. Every message names the thing that is wrong: the
stage, prim, file, frame, channel or color space, and the value seen."""

from __future__ import annotations


class UsdHarmonizerError(Exception):
    """Base class of every error the USD hook raises on bad input."""


class SettingsError(UsdHarmonizerError):
    """The stage has no usable RenderSettings, product or frame range."""


class VarError(UsdHarmonizerError):
    """A RenderVar is missing, or its channels are not in the product's file."""


class CameraError(UsdHarmonizerError):
    """The camera of a product is missing or is not a UsdGeom.Camera."""


class ColorSpaceError(UsdHarmonizerError):
    """A declared color space is unknown to the OpenColorIO config."""


class ProductFileError(UsdHarmonizerError):
    """A product's file for a frame is missing or unreadable."""


class FrameError(UsdHarmonizerError):
    """Enhancing or writing one frame failed (the temporal state is unchanged)."""


class BindingError(UsdHarmonizerError):
    """The harmonizer Python binding or its library cannot be found."""
