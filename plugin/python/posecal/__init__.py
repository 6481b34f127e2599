"""posecal: camera calibration with efficient pose selection, from Python.

A pure-Python (ctypes) binding of libposecal.so's C ABI (posecal.h), no compiled extension;
images are numpy arrays. Typical use::

    import posecal

    with posecal.Context() as ctx, ctx.open("sim://?seed=1") as session:
        for event in session:              # steps the camera, yields the session's events
            print(event.kind, event.data)
        result = session.result            # a dict, plus numpy arrays result.K and result.D
        print(result["converged"], result.K, result.D)
        session.save("camera.yml")

A host with its own camera feeds its frames, H x W (grey) or H x W x 3 (BGR) uint8 arrays such
as cv2.VideoCapture's, to an "external" session: `session.feed(frame)`; `last_frame()` and
`render_overlay()` return such arrays.

Threads: a Context may be shared by threads; each Session is used by one thread at a time
(different sessions on different threads run concurrently: the library releases the GIL while
it works). Events are queued by the library's callback on the thread that steps the session and
are read from the queue by `events()`, iteration or `pending_events()`.

Errors raise PosecalError subclasses carrying `status`, `status_name` and `message`; each
also derives from the matching builtin (errors.py): InvalidArgumentError is a ValueError,
TimeoutError the builtin TimeoutError, FileError an OSError, ...

`__version__` is this package's version (pyproject.toml reads it from _version.py); `version()`
is the loaded library's (posecal_version()). They are equal when both come from one build; the
binding works with any library of ABI version `_native.ABI_VERSION`.
"""

from __future__ import annotations

import collections
import ctypes
import json
import os
import threading
import warnings
import weakref
from typing import (Any, Callable, Deque, Dict, Iterable, Iterator, List, NamedTuple, Optional,
                    Tuple, TypeVar, Union, overload)

import numpy as np
import numpy.typing as npt

from . import _native
from ._image import Buffer, Frame, PixelFormat, from_array, host_image, new_frame
from ._result import Result
from ._version import __version__
from .errors import (
    BufferTooSmallError,
    DegenerateError,
    DeviceError,
    FileError,
    InternalError,
    InvalidArgumentError,
    InvalidTypeError,
    NotFoundError,
    PosecalError,
    StateError,
    TimeoutError,
    UnsupportedError,
    error_for,
)
from . import errors as _errors

#: A file name: str, bytes or os.PathLike.
PathArg = Union[str, bytes, "os.PathLike[str]"]

_H = TypeVar("_H", bound="_Handle")

__all__ = [
    "Context",
    "Session",
    "Calibration",
    "Event",
    "PixelFormat",
    "Result",
    "Frame",
    "PosecalError",
    "InvalidArgumentError",
    "InvalidTypeError",
    "NotFoundError",
    "BufferTooSmallError",
    "TimeoutError",
    "DeviceError",
    "StateError",
    "FileError",
    "InternalError",
    "DegenerateError",
    "UnsupportedError",
    "abi_version",
    "version",
    "__version__",
    "library_path",
    "write_target",
    "records_list",
    "records_show",
    "records_resolve",
    "records_export",
    "records_import",
    "records_report",
]

_lib = _native.lib
library_path = _native.library_path


def _error(status: int) -> PosecalError:
    """The exception for a failed call; must run before any other posecal call on this thread
    (the message is per thread and reset by the next successful call)."""
    message = (_lib.posecal_last_error() or b"").decode("utf-8", "replace")
    return error_for(status, message)


def _check(status: int) -> None:
    if status != _errors.OK:
        raise _error(status)


def _enc(text: Optional[PathArg], name: str) -> Optional[bytes]:
    if text is None:
        return None
    if isinstance(text, os.PathLike):
        text = os.fspath(text)
    if isinstance(text, bytes):
        return text
    if not isinstance(text, str):
        raise InvalidTypeError(_errors.E_INVALID_ARGUMENT, "%s must be a string" % name)
    return text.encode("utf-8")


def _options(options: Optional[Dict[str, Any]]) -> Optional[bytes]:
    """A dict of options as the JSON object the C ABI takes (None: defaults)."""
    if not options:
        return None
    return json.dumps(options).encode("utf-8")


def _fetch_json(call: Callable[[Any, Any], int]) -> Any:
    """Calls a JSON-returning function with the size protocol and parses the result."""
    size = ctypes.c_size_t(65536)
    buf = ctypes.create_string_buffer(size.value)
    status = call(buf, ctypes.byref(size))
    if status == _errors.E_BUFFER_TOO_SMALL:
        buf = ctypes.create_string_buffer(size.value)
        status = call(buf, ctypes.byref(size))
    _check(status)
    return json.loads(buf.value.decode("utf-8"))


def abi_version() -> int:
    """POSECAL_ABI_VERSION of the loaded library."""
    return int(_lib.posecal_abi_version())


def version() -> str:
    """The loaded library's version (posecal_version()), e.g. "0.1.0"; `__version__` is the
    package's."""
    return _lib.posecal_version().decode("utf-8")


def records_list(db: PathArg) -> List[Dict[str, Any]]:
    """The runs of a record store (the session key "records"; a station keeps
    DIR/records.sqlite), newest first: run_id, station_id, operator_id, lens_id, camera,
    posecal_version, abi_version, started, finished, state, verdict, expected_error_px,
    keyframes (posecal.h, posecal_records_list)."""
    d = _enc(db, "db")
    runs: List[Dict[str, Any]] = _fetch_json(lambda b, n: _lib.posecal_records_list(d, b, n))
    return runs


def records_show(db: PathArg, run_id: str) -> Dict[str, Any]:
    """One run (its id or a unique prefix): the list's fields and config, image size,
    locked_settings, result (None without a calibration) and keyframes."""
    d, r = _enc(db, "db"), _enc(run_id, "run_id")
    run: Dict[str, Any] = _fetch_json(lambda b, n: _lib.posecal_records_show(d, r, b, n))
    return run


def records_resolve(db: PathArg, run_id: str) -> Dict[str, Any]:
    """Re-solves a run from its stored detections: identical (bit for bit with the stored
    result), recomputed and stored intrinsics."""
    d, r = _enc(db, "db"), _enc(run_id, "run_id")
    out: Dict[str, Any] = _fetch_json(lambda b, n: _lib.posecal_records_resolve(d, r, b, n))
    return out


def records_export(db: PathArg, run_id: str, path: PathArg, format: Optional[str] = None) -> None:
    """Writes a run's re-solved calibration as a model file (format by name, or by the
    extension)."""
    _check(_lib.posecal_records_export(_enc(db, "db"), _enc(run_id, "run_id"), _enc(path, "path"),
                                       _enc(format, "format")))


def records_import(db: PathArg, journal: PathArg, **options: Any) -> Dict[str, Any]:
    """Records a session's journal as a run (the spool of a run whose store was away).
    options: run_id, station_id, operator_id, lens_id. Returns run_id, keyframes, state,
    journal_note."""
    d, j, o = _enc(db, "db"), _enc(journal, "journal"), _options(options)
    out: Dict[str, Any] = _fetch_json(lambda b, n: _lib.posecal_records_import(d, j, o, b, n))
    return out


def records_report(html: PathArg, db: Optional[PathArg] = None, run_id: Optional[str] = None,
                   result: Optional[PathArg] = None, pdf: Optional[PathArg] = None) -> Dict[str, Any]:
    """Writes the calibration report as self-contained HTML (every figure embedded) and, with
    `pdf`, a PDF: of a recorded run (`db` and `run_id`: coverage, residuals, distortion,
    expected-error map, sigma after each keyframe, verdict and fleet position) or of a result
    file (`result`: distortion and expected-error map). Returns html, pdf, plots (the figure
    ids), pages and notes (posecal.h, posecal_records_report)."""
    d, r, f = _enc(db, "db"), _enc(run_id, "run_id"), _enc(result, "result")
    h, p = _enc(html, "html"), _enc(pdf, "pdf")
    out: Dict[str, Any] = _fetch_json(lambda b, n: _lib.posecal_records_report(d, r, f, h, p, b, n))
    return out


def write_target(path: PathArg, target: Optional[str] = None, dpi: float = 300.0,
                 margin_m: float = 0.01, paper: Optional[str] = None) -> None:
    """Writes the printable target at exact scale: .pdf (vector) or .png at `dpi`
    (docs/board.md). paper: None or "board" (a page of the board's size), "a4", "a3" or
    "letter" (the board on such sheets, tiled with cut marks when it does not fit one; each
    page with the specification, a 100 mm ruler and "print at 100 %"); PDF only."""
    options: Dict[str, Any] = {"dpi": float(dpi), "margin_m": float(margin_m)}
    if paper is not None:
        options["paper"] = paper
    _check(_lib.posecal_write_target_ex(_enc(target, "target"), _enc(path, "path"),
                                        json.dumps(options).encode("utf-8")))


class Event(NamedTuple):
    """A session event: `kind` ("captured", "state_changed", ...) and `data`, the JSON payload
    as a dict (keys "keyframes", "frames", "message", ...)."""

    kind: str
    data: Dict[str, Any]


class _Handle:
    """An owned library handle: close() frees it (also at collection and on leaving a `with`);
    calls on a closed object raise StateError."""

    _what = "object"
    _h: Optional[ctypes.c_void_p] = None

    def close(self) -> None:
        raise NotImplementedError

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # interpreter shutdown: the library may be gone already
            pass

    def __enter__(self: _H) -> _H:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        return not self._h

    def _handle(self) -> ctypes.c_void_p:
        if not self._h:
            raise StateError(_errors.E_STATE, "the %s is closed" % self._what)
        return self._h


class Calibration(_Handle):
    """The result of Context.calibrate_images(): `.result` and `.save(path)`."""

    _what = "calibration"

    def __init__(self, handle: ctypes.c_void_p) -> None:
        self._h = handle

    def close(self) -> None:
        if self._h:
            _lib.posecal_calibration_destroy(self._h)
            self._h = None

    @property
    def result(self) -> Result:
        """The calibration: a dict of posecal_calibration_json's object, with `K`, `D` and
        `covariance` as numpy arrays (Result)."""
        h = self._handle()
        return Result(_fetch_json(lambda b, n: _lib.posecal_calibration_json(h, b, n)))

    def save(self, path: PathArg, format: Optional[str] = None) -> None:
        """Saves the calibration: by the extension (.yml/.yaml/.json/.xml OpenCV, .cameramodel
        mrcal), or in ``format`` ("opencv", "ros", "mrcal", "kalibr", "halcon";
        docs/formats.md).
        InvalidArgumentError, nothing written, for a model the format cannot hold."""
        _check(_lib.posecal_calibration_save_as(self._handle(), _enc(path, "path"),
                                                _enc(format, "format")))


class Context(_Handle):
    """Camera backends shared by sessions (posecal_context). Thread-safe.

    backends: None for all, or a list of "sim", "images", "external", "aravis", "v4l2".
    """

    _what = "context"

    def __init__(self, backends: Optional[Iterable[str]] = None) -> None:
        self._h = None
        # Open sessions (weakly: a forgotten session is still closed when it is collected),
        # closed before the context.
        self._sessions: "weakref.WeakSet[Session]" = weakref.WeakSet()
        self._sessions_lock = threading.Lock()
        opts = None if backends is None else {"backends": list(backends)}
        h = ctypes.c_void_p()
        _check(_lib.posecal_context_create(_options(opts), ctypes.byref(h)))
        self._h = h

    def close(self) -> None:
        """Closes every session still open on the context, then the context."""
        if self._h:
            with self._sessions_lock:
                sessions = list(self._sessions)
            for s in sessions:
                s.close()
            _lib.posecal_context_destroy(self._h)
            self._h = None

    def cameras(self) -> List[Dict[str, Any]]:
        """Cameras of every enabled backend (list of dicts: uri, backend, id, vendor, ...)."""
        h = self._handle()
        return _fetch_json(lambda b, n: _lib.posecal_list_cameras(h, b, n))

    def features(self, uri: str) -> List[Dict[str, Any]]:
        """The camera's settings: list of dicts (name, type, value, access, unit, range,
        options)."""
        h = self._handle()
        u = _enc(uri, "uri")
        return _fetch_json(lambda b, n: _lib.posecal_camera_features(h, u, b, n))

    def grab(self, uri: str, count: int, out_dir: PathArg,
             timeout_ms: int = 10000) -> Dict[str, Any]:
        """Saves `count` frames as PNG files in out_dir; returns the list of files and more."""
        h = self._handle()
        u, d = _enc(uri, "uri"), _enc(out_dir, "out_dir")
        return _fetch_json(
            lambda b, n: _lib.posecal_camera_grab(h, u, int(count), d, int(timeout_ms), b, n))

    def evaluate(self, result_path: PathArg, uri: str, **options: Any) -> Dict[str, Any]:
        """Test-set error of a calibration file on a camera (eps_test; eps_gt for sim://).
        options: target, frames, min_corners, timeout_ms."""
        h = self._handle()
        r, u, o = _enc(result_path, "result_path"), _enc(uri, "uri"), _options(options)
        return _fetch_json(lambda b, n: _lib.posecal_evaluate(h, r, u, o, b, n))

    def calibrate_images(self, images_dir: PathArg, target: Optional[str] = None,
                         progress: Optional[Callable[[Dict[str, Any]], None]] = None,
                         **options: Any) -> Calibration:
        """Offline calibration of a folder of images; returns a Calibration.
        options: fix_principal_point, fix_aspect_ratio, zero_tangential, fixed, min_corners,
        camera_group (where the folder mixes cameras or image sizes: a group's name such as
        "left@640x480", its camera "left" or its size "640x480"; without it such a folder raises
        InvalidArgumentError listing the groups), spec (a quality specification file: the
        result gets "verdict" and "verdict_reasons"). progress: called after each image with a dict
        {"index", "total", "file", "corners", "used", "reason"}; an exception it raises is
        printed by ctypes and does not stop the calibration."""
        h = ctypes.c_void_p()
        # A callback that reports nothing without `progress` (kept alive for the call).
        callback = _native.EVENT_FN(
            lambda _user, _kind, payload: progress(json.loads(payload)) if progress else None)
        _check(_lib.posecal_calibrate_images_ex(self._handle(), _enc(images_dir, "images_dir"),
                                                _enc(target, "target"), _options(options),
                                                callback, None, ctypes.byref(h)))
        return Calibration(h)

    def open(self, uri: str, **config: Any) -> Session:
        """Opens a calibration session on a camera. config: the keys of posecal_session_open
        (core/session/session_keys.def): method, target, operator, convergence_threshold, max_keyframes,
        jaccard_threshold, still_motion_px, track_board, constraint_factor, target_timeout_frames,
        pose_candidates, lock_settings, max_tilt_deg, lens_model, fixed, convergence_measure,
        measured_convergence, candidate_score, view_candidates, view_must_serve_target,
        board_timeout_s, accuracy_px, ratio_stop_max_p90_px, journal, journal_images, resume, spec,
        records, records_spool, fleet_outlier_probability, prior, run_id, station_id, operator_id, lens_id.
        lens_model="auto" lets the engine choose the lens model by the BIC (the result's
        lens_model_choice holds the evidence)."""
        return Session(self, uri, **config)


def _queueing_callback(queue: Deque[Event]) -> Callable[[Any, bytes, bytes], None]:
    def on_event(_user: Any, kind: bytes, payload: bytes) -> None:
        try:
            data = json.loads(payload.decode("utf-8"))
        except ValueError:
            data = {"payload": payload.decode("utf-8", "replace")}
        queue.append(Event(kind.decode("utf-8"), data))

    return on_event


class Session(_Handle):
    """One camera calibrated by the pose-selection engine (posecal_session).

    Iterating a session steps it until the calibration finishes, yielding its events.
    """

    _what = "session"

    def __init__(self, context: Context, uri: str, **config: Any) -> None:
        self._h = None
        self._context = context
        self._events: Deque[Event] = collections.deque()
        self._finished = False
        h = ctypes.c_void_p()
        _check(_lib.posecal_session_open(context._handle(), _enc(uri, "uri"), _options(config),
                                         ctypes.byref(h)))
        self._h = h
        with context._sessions_lock:
            context._sessions.add(self)
        # The C callback only queues: it runs on the stepping thread, inside step()/feed(). It
        # holds the queue, not the session, so a dropped session is freed (and closed) at once.
        self._callback = _native.EVENT_FN(_queueing_callback(self._events))
        _check(_lib.posecal_session_set_callback(self._h, self._callback, None))

    def close(self) -> None:
        if self._h:
            _lib.posecal_session_close(self._h)
            self._h = None
            with self._context._sessions_lock:
                self._context._sessions.discard(self)

    # ---- frames --------------------------------------------------------------------------
    def step(self, timeout_ms: int = 1000) -> bool:
        """Processes one frame of the camera. Returns True if a frame was processed, False once
        the calibration has finished. Raises TimeoutError (no frame in time), DeviceError
        (camera disconnected: keep stepping), NotFoundError (images:// ended)."""
        status = _lib.posecal_session_step(self._handle(), int(timeout_ms))
        if status == _errors.OK:
            return True
        error = _error(status)
        if status == _errors.E_STATE and self.finished:
            return False
        raise error

    def feed(self, data: Union[Frame, Buffer], width: Optional[int] = None,
             height: Optional[int] = None, stride: Optional[int] = None,
             format: Optional[int] = None) -> None:
        """Processes a host frame.

        A numpy array is passed alone: uint8, H x W (grey) or H x W x 3 (BGR; `format=
        PixelFormat.RGB8` for RGB); any view works (one whose rows the library cannot read in
        place, such as a reversed one, is copied first), read-only ones too. Another dtype or
        shape raises InvalidArgumentError (a ValueError; a TypeError too for the dtype).

        A raw buffer (bytes, bytearray, memoryview) needs `width` and `height`; `format`
        (default MONO8) and `stride` (bytes between rows, default packed) describe it."""
        img = host_image(data, width, height, stride, format, writable=False)
        _check(_lib.posecal_session_feed(self._handle(), img.ref()))

    def _frame_size(self) -> Tuple[int, int]:
        st = self.status
        if st.get("image_width") is None:
            raise StateError(_errors.E_STATE, "no frame processed yet")
        return st["image_width"], st["image_height"]

    def last_frame(self, format: int = PixelFormat.BGR8, with_overlay: bool = False) -> Frame:
        """The last processed frame as a new numpy array: H x W x 3 uint8 (BGR, or RGB with
        `format=PixelFormat.RGB8`; ready for cv2.imwrite/imshow) or H x W (MONO8), optionally
        with the guidance overlay drawn into it. Raises StateError before the first frame."""
        w, h = self._frame_size()
        frame = new_frame(w, h, format)
        img = from_array(frame, format, writable=True)
        _check(_lib.posecal_session_last_frame(self._handle(), img.ref()))
        if with_overlay:
            _check(_lib.posecal_session_render_overlay(self._handle(), img.ref()))
        return frame

    def last_frame_buffer(self, format: int = PixelFormat.BGR8,
                          with_overlay: bool = False) -> Tuple[bytearray, int, int, int]:
        """Deprecated: last_frame()'s form before numpy, (bytearray, width, height, stride)."""
        warnings.warn("Session.last_frame_buffer() is deprecated: last_frame() returns the frame "
                      "as a numpy array (frame.shape gives its size, frame.tobytes() its bytes)",
                      DeprecationWarning, stacklevel=2)
        frame = self.last_frame(format, with_overlay)
        return bytearray(frame.tobytes()), frame.shape[1], frame.shape[0], frame.strides[0]

    @overload
    def render_overlay(self, image: None = None, *, format: Optional[int] = None) -> Frame: ...

    @overload
    def render_overlay(self, image: Frame, *, format: Optional[int] = None) -> Frame: ...

    @overload
    def render_overlay(self, image: Buffer, width: int, height: int,
                       stride: Optional[int] = None, format: Optional[int] = None) -> None: ...

    def render_overlay(self, image: Union[Frame, Buffer, None] = None,
                       width: Optional[int] = None, height: Optional[int] = None,
                       stride: Optional[int] = None,
                       format: Optional[int] = None) -> Optional[Frame]:
        """Draws the guidance overlay (target board, detected corners, text).

        - No image: returns the last frame with the overlay, a new array (as
          `last_frame(format or BGR8, with_overlay=True)`).
        - A numpy array of the camera's size (see feed(); BGR unless `format` says otherwise):
          draws into it in place and returns it. It must be writable; a view the library cannot
          draw into in place is drawn through a copy.
        - A writable raw buffer (bytearray, memoryview) with `width` and `height` (`format`
          default BGR8): draws into it in place and returns None, as before numpy."""
        if image is None:
            if width is not None or height is not None or stride is not None:
                raise InvalidTypeError(_errors.E_INVALID_ARGUMENT,
                                       "render_overlay(): width, height and stride go with an "
                                       "image buffer")
            return self.last_frame(PixelFormat.BGR8 if format is None else format,
                                   with_overlay=True)
        array = isinstance(image, np.ndarray) and width is None and height is None
        if not array and format is None:
            format = PixelFormat.BGR8
        img = host_image(image, width, height, stride, format, writable=True)
        _check(_lib.posecal_session_render_overlay(self._handle(), img.ref()))
        img.write_back()
        return image if isinstance(image, np.ndarray) and array else None

    def expected_error_map(self, width: int = 40, height: int = 23) -> npt.NDArray[np.float32]:
        """The predicted RMS projection error in pixels at width x height points from image edge
        to image edge (posecal_session_expected_error_map), as a (height, width) float32 array
        (NaN where the lens has no ray). Raises StateError before the second keyframe."""
        grid = np.empty((int(height), int(width)), dtype=np.float32)
        _check(_lib.posecal_session_expected_error_map(
            self._handle(), grid.ctypes.data_as(ctypes.POINTER(ctypes.c_float)), int(width),
            int(height), 0))
        return grid

    # ---- robot mode -----------------------------------------------------------------------
    def pose_reached(self) -> None:
        """Robot mode: the robot is at the current target."""
        _check(_lib.posecal_session_pose_reached(self._handle()))

    def skip_target(self) -> None:
        """Gives up on the current refinement target."""
        _check(_lib.posecal_session_skip_target(self._handle()))

    def interrupt(self) -> None:
        """Stops the calibration gracefully (any thread): no further frame is processed,
        status and result say "interrupted", and the calibration so far can be saved."""
        _check(_lib.posecal_session_interrupt(self._handle()))

    # ---- state ----------------------------------------------------------------------------
    @property
    def status(self) -> Dict[str, Any]:
        """The session's status (dict: state, keyframes, guidance, parameters, ...)."""
        h = self._handle()
        st = _fetch_json(lambda b, n: _lib.posecal_session_status(h, b, n))
        self._finished = bool(st.get("finished"))
        return st

    @property
    def finished(self) -> bool:
        """True once the calibration has converged or failed."""
        if not self._finished and self._h:
            self.status  # noqa: B018 - refreshes _finished
        return self._finished

    @property
    def converged(self) -> bool:
        """True once the calibration has converged."""
        return self.status["state"] == "converged"

    @property
    def result(self) -> Optional[Result]:
        """The current calibration, or None before the second keyframe: a dict of
        posecal_session_result's object, with `K`, `D` and `covariance` as numpy arrays
        (Result)."""
        h = self._handle()
        try:
            return Result(_fetch_json(lambda b, n: _lib.posecal_session_result(h, b, n)))
        except StateError:
            return None

    @property
    def target_pose(self) -> Optional[Tuple[Tuple[float, ...], Tuple[float, ...]]]:
        """The board pose to reach as (rvec, tvec) in the camera frame (metres), or None when
        there is no target."""
        r = (ctypes.c_double * 3)()
        t = (ctypes.c_double * 3)()
        status = _lib.posecal_session_target_pose(self._handle(), r, t)
        if status == _errors.E_STATE:
            return None
        _check(status)
        return tuple(r), tuple(t)

    def save(self, path: PathArg, format: Optional[str] = None) -> None:
        """Saves the calibration: by the extension (.yml/.yaml/.json/.xml OpenCV, .cameramodel
        mrcal), or in ``format`` ("opencv", "ros", "mrcal", "kalibr", "halcon";
        docs/formats.md).
        StateError before two keyframes; InvalidArgumentError, nothing written, for a model the
        format cannot hold."""
        _check(_lib.posecal_session_save_as(self._handle(), _enc(path, "path"),
                                            _enc(format, "format")))

    # ---- events ---------------------------------------------------------------------------
    def pending_events(self) -> List[Event]:
        """The events queued so far (and removes them from the queue)."""
        out: List[Event] = []
        while self._events:
            out.append(self._events.popleft())
        return out

    def events(self, timeout_ms: int = 1000,
               max_frames: Optional[int] = None) -> Iterator[Event]:
        """Steps the session until it finishes (or max_frames frames), yielding every event as
        it is queued. Timeouts and disconnects are yielded as Event("timeout"/"disconnected")
        and stepping goes on; a finite source's end stops the iteration."""
        frames = 0
        while max_frames is None or frames < max_frames:
            more = True
            try:
                more = self.step(timeout_ms)
                frames += 1
            except TimeoutError as e:
                self._events.append(Event("timeout", {"message": e.message}))
            except DeviceError as e:
                self._events.append(Event("disconnected", {"message": e.message}))
            except NotFoundError:
                more = False
            while self._events:
                yield self._events.popleft()
            if not more:
                break
        while self._events:
            yield self._events.popleft()

    def __iter__(self) -> Iterator[Event]:
        return self.events()

    def run(self, timeout_ms: int = 1000, max_frames: Optional[int] = None) -> Optional[Result]:
        """Steps until the calibration finishes; returns the result (None without one)."""
        for _ in self.events(timeout_ms, max_frames):
            pass
        return self.result
