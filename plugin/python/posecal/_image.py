"""Host images for the C ABI: numpy arrays and raw buffers described as a posecal_image.

A numpy array carries its own width, height, channel count and row stride; a raw buffer (bytes,
bytearray, memoryview) needs them from the caller. The library reads or writes `data` only
during the call, so what keeps the memory alive is held by the HostImage until the call returns.
"""

from __future__ import annotations

import ctypes
from typing import Any, Optional, Tuple, Union

import numpy as np
import numpy.typing as npt

from . import _native
from . import errors as _errors
from .errors import InvalidArgumentError, InvalidTypeError

#: What feed() and render_overlay() take besides numpy arrays (with width and height).
Buffer = Union[bytes, bytearray, memoryview]

#: An 8-bit image: H x W (grey) or H x W x 3 (BGR or RGB).
Frame = npt.NDArray[np.uint8]

# posecal.h: width and height in 1..65535, stride_bytes an int32 >= width x bytes per pixel.
_MAX_SIDE = 65535
_MAX_STRIDE = 0x7FFFFFFF


class PixelFormat:
    """posecal_pixel_format: the layout of an 8-bit image's pixels."""

    MONO8 = 0
    BGR8 = 1
    RGB8 = 2

    CHANNELS = {MONO8: 1, BGR8: 3, RGB8: 3}


def _invalid(message: str) -> InvalidArgumentError:
    return InvalidArgumentError(_errors.E_INVALID_ARGUMENT, message)


def _wrong_type(message: str) -> InvalidTypeError:
    return InvalidTypeError(_errors.E_INVALID_ARGUMENT, message)


def _check_format(fmt: object) -> int:
    if fmt not in PixelFormat.CHANNELS:
        raise _invalid("unknown pixel format %r (PixelFormat.MONO8, BGR8 or RGB8)" % (fmt,))
    return fmt  # type: ignore[return-value]


class HostImage:
    """A posecal_image over host memory and what keeps that memory alive. For an array drawn
    into through a copy (a layout stride_bytes cannot express), write_back() copies the pixels
    to the caller's array."""

    __slots__ = ("image", "_keep", "_target")

    def __init__(self, width: int, height: int, stride: int, fmt: int, address: int,
                 keep: object, target: Optional[Frame] = None) -> None:
        self.image = _native.Image(ctypes.sizeof(_native.Image), width, height, stride, fmt,
                                   address)
        self._keep = keep
        self._target = target

    def ref(self) -> "ctypes._CArgObject":
        return ctypes.byref(self.image)

    def write_back(self) -> None:
        if self._target is not None:
            self._target[...] = self._keep


def array_format(shape: Tuple[int, ...], fmt: Optional[int]) -> int:
    """The pixel format of an image array of `shape`: H x W is MONO8 (so is H x W x 1),
    H x W x 3 is BGR8 unless `fmt` says RGB8. Anything else raises InvalidArgumentError (a
    ValueError) naming what was expected."""
    if fmt is not None:
        _check_format(fmt)
    grey = len(shape) == 2 or (len(shape) == 3 and shape[2] == 1)
    color = len(shape) == 3 and shape[2] == 3
    if not (grey or color):
        raise _invalid("image: expected an H x W (grey) or H x W x 3 (BGR or RGB) uint8 array, "
                       "got shape %s" % (tuple(shape),))
    if grey:
        if fmt not in (None, PixelFormat.MONO8):
            raise _invalid("image: format BGR8/RGB8 needs an H x W x 3 array, got shape %s "
                           "(grey)" % (tuple(shape),))
        return PixelFormat.MONO8
    if fmt == PixelFormat.MONO8:
        raise _invalid("image: format MONO8 needs an H x W array, got shape %s (3 channels)"
                       % (tuple(shape),))
    return PixelFormat.BGR8 if fmt is None else fmt


def _row_stride(array: Frame, channels: int) -> Optional[int]:
    """The row stride in bytes if the library can read `array` in place: pixels packed within
    a row, rows a positive stride apart that posecal_image's int32 can hold; else None."""
    h, w = array.shape[:2]
    if channels == 3 and array.strides[2] != 1:
        return None
    if w > 1 and array.strides[1] != channels:
        return None
    row = w * channels
    if h == 1:
        return row  # numpy may give a single row any stride: it is never used
    stride = array.strides[0]
    return stride if row <= stride <= _MAX_STRIDE else None


def from_array(array: npt.NDArray[Any], fmt: Optional[int], writable: bool) -> HostImage:
    """A HostImage over a numpy image array (see array_format). An array whose layout
    posecal_image cannot describe (a reversed, transposed or column-sliced view) is copied with
    np.ascontiguousarray; when `writable`, the library draws into that copy and write_back()
    copies it to `array`. A read-only array is refused only when `writable`."""
    if array.dtype != np.uint8:
        raise _wrong_type("image: expected a uint8 array (8 bits per channel), got dtype %s"
                          % array.dtype)
    fmt = array_format(array.shape, fmt)
    h, w = array.shape[:2]
    if not (1 <= w <= _MAX_SIDE and 1 <= h <= _MAX_SIDE):
        raise _invalid("image: width and height must be in 1..%d, got shape %s"
                       % (_MAX_SIDE, array.shape))
    if writable and not array.flags.writeable:
        raise _invalid("image: the array is read-only and the overlay is drawn in place; "
                       "pass a writable copy (array.copy())")
    channels = PixelFormat.CHANNELS[fmt]
    stride = _row_stride(array, channels)
    target = None
    if stride is None:
        if writable:
            target = array
        array = np.ascontiguousarray(array)
        stride = w * channels
    return HostImage(w, h, stride, fmt, array.ctypes.data, array, target)


def from_buffer(data: object, width: int, height: int, stride: Optional[int], fmt: int,
                writable: bool) -> HostImage:
    """A HostImage over a raw buffer, after checking that the buffer is large enough (the
    library cannot check a raw pointer)."""
    for name, v in (("width", width), ("height", height)):
        if not isinstance(v, int) or not 1 <= v <= _MAX_SIDE:
            raise _invalid("%s must be an integer in 1..%d" % (name, _MAX_SIDE))
    _check_format(fmt)
    if isinstance(data, np.ndarray) and data.dtype != np.uint8:
        raise _wrong_type("image: expected uint8 pixels, got a %s array" % data.dtype)
    row = width * PixelFormat.CHANNELS[fmt]
    if stride is None:
        stride = row
    if not isinstance(stride, int) or not row <= stride <= _MAX_STRIDE:
        raise _invalid("stride must be an integer >= width x channels (%d)" % row)
    needed = stride * (height - 1) + row
    try:
        view = memoryview(data)  # type: ignore[arg-type]
    except TypeError:
        raise _wrong_type(
            "image data must be a numpy uint8 array, or bytes, bytearray or another buffer "
            "with width and height, not %s" % type(data).__name__) from None
    if view.nbytes < needed:
        raise _invalid("buffer has %d bytes, a %dx%d image with stride %d needs %d"
                       % (view.nbytes, width, height, stride, needed))
    keep: object
    if isinstance(data, bytes) and not writable:
        keep = data
        address = ctypes.cast(ctypes.c_char_p(data), ctypes.c_void_p).value
    elif not view.readonly and view.c_contiguous:
        flat = view if (view.ndim == 1 and view.format == "B") else view.cast("B")
        keep = (ctypes.c_char * flat.nbytes).from_buffer(flat)
        address = ctypes.addressof(keep)
    elif writable:
        raise _invalid("the image buffer must be writable (bytearray, memoryview)")
    else:
        keep = bytes(view)  # a read-only or strided buffer: one copy
        address = ctypes.cast(ctypes.c_char_p(keep), ctypes.c_void_p).value
    assert address is not None
    return HostImage(width, height, stride, fmt, address, keep)


def host_image(data: object, width: Optional[int], height: Optional[int],
               stride: Optional[int], fmt: Optional[int], writable: bool) -> HostImage:
    """feed()'s and render_overlay()'s image: a numpy array alone, or a buffer with its width
    and height (the form before numpy; numpy arrays are buffers too)."""
    if width is None and height is None and stride is None and isinstance(data, np.ndarray):
        return from_array(data, fmt, writable)
    if width is None or height is None:
        if isinstance(data, np.ndarray):
            raise _wrong_type("pass a numpy array alone (its shape and strides give width, "
                              "height and stride), or width and height with it")
        raise _wrong_type("image: expected a numpy uint8 array (H x W or H x W x 3), or a "
                          "buffer with width and height; got %s without width and height"
                          % type(data).__name__)
    return from_buffer(data, width, height, stride,
                       PixelFormat.MONO8 if fmt is None else fmt, writable)


def new_frame(width: int, height: int, fmt: int) -> Frame:
    """An uninitialised image array of the camera's size in `fmt`."""
    channels = PixelFormat.CHANNELS[_check_format(fmt)]
    shape = (height, width) if channels == 1 else (height, width, channels)
    return np.empty(shape, np.uint8)
