"""posecal: camera calibration with efficient pose selection, from Python.

A pure-Python (ctypes) binding of libposecal.so's C ABI (posecal.h); no compiled extension and
no numpy. Typical use::

    import posecal

    with posecal.Context() as ctx, ctx.open("sim://?seed=1") as session:
        for event in session:              # steps the camera, yields the session's events
            print(event.kind, event.data)
        print(session.result["converged"], session.result["fx"])
        session.save("camera.yml")

Threads: a Context may be shared by threads; each Session is used by one thread at a time
(different sessions on different threads run concurrently: the library releases the GIL while
it works). Events are queued by the library's callback on the thread that steps the session and
are read from the queue by `events()`, iteration or `pending_events()`.

Errors raise PosecalError subclasses carrying `status`, `status_name` and `message`.
"""

import collections
import ctypes
import json
import os
import threading
import weakref

from . import _native
from .errors import (
    BufferTooSmallError,
    DegenerateError,
    DeviceError,
    FileError,
    InternalError,
    InvalidArgumentError,
    NotFoundError,
    PosecalError,
    StateError,
    TimeoutError,
    UnsupportedError,
    error_for,
)
from . import errors as _errors

__all__ = [
    "Context",
    "Session",
    "Calibration",
    "Event",
    "PixelFormat",
    "PosecalError",
    "InvalidArgumentError",
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
    "library_path",
    "write_target",
]

_lib = _native.lib
library_path = _native.library_path


class PixelFormat:
    """posecal_pixel_format."""

    MONO8 = 0
    BGR8 = 1
    RGB8 = 2

    CHANNELS = {MONO8: 1, BGR8: 3, RGB8: 3}


def _error(status):
    """The exception for a failed call; must run before any other posecal call on this thread
    (the message is per thread and reset by the next successful call)."""
    message = (_lib.posecal_last_error() or b"").decode("utf-8", "replace")
    return error_for(status, message)


def _check(status):
    if status != _errors.OK:
        raise _error(status)


def _enc(text, name):
    if text is None:
        return None
    if isinstance(text, os.PathLike):
        text = os.fspath(text)
    if isinstance(text, bytes):
        return text
    if not isinstance(text, str):
        raise InvalidArgumentError(_errors.E_INVALID_ARGUMENT, "%s must be a string" % name)
    return text.encode("utf-8")


def _options(options):
    """A dict of options as the JSON object the C ABI takes (None: defaults)."""
    if not options:
        return None
    return json.dumps(options).encode("utf-8")


def _fetch_json(call):
    """Calls a JSON-returning function with the size protocol and parses the result."""
    size = ctypes.c_size_t(65536)
    buf = ctypes.create_string_buffer(size.value)
    status = call(buf, ctypes.byref(size))
    if status == _errors.E_BUFFER_TOO_SMALL:
        buf = ctypes.create_string_buffer(size.value)
        status = call(buf, ctypes.byref(size))
    _check(status)
    return json.loads(buf.value.decode("utf-8"))


def abi_version():
    """POSECAL_ABI_VERSION of the loaded library."""
    return int(_lib.posecal_abi_version())


def version():
    """Library version, e.g. "0.1.0"."""
    return _lib.posecal_version().decode("utf-8")


def write_target(path, target=None, dpi=300.0, margin_m=0.01):
    """Writes the printable target at exact scale (.pdf vector, .png at `dpi`)."""
    _check(_lib.posecal_write_target(_enc(target, "target"), _enc(path, "path"), float(dpi),
                                     float(margin_m)))


def _image_view(data, width, height, stride, fmt, writable):
    """A posecal_image over a Python buffer, after checking that the buffer is large enough
    (the library cannot check a raw pointer). Returns (image, keepalive)."""
    for name, v in (("width", width), ("height", height)):
        if not isinstance(v, int) or not 1 <= v <= 65535:
            raise InvalidArgumentError(_errors.E_INVALID_ARGUMENT,
                                       "%s must be an integer in 1..65535" % name)
    if fmt not in PixelFormat.CHANNELS:
        raise InvalidArgumentError(_errors.E_INVALID_ARGUMENT, "unknown pixel format %r" % (fmt,))
    row = width * PixelFormat.CHANNELS[fmt]
    if stride is None:
        stride = row
    if not isinstance(stride, int) or not row <= stride <= 0x7FFFFFFF:
        raise InvalidArgumentError(_errors.E_INVALID_ARGUMENT,
                                   "stride must be an integer >= width x channels (%d)" % row)
    needed = stride * (height - 1) + row
    try:
        view = memoryview(data)
    except TypeError:
        raise InvalidArgumentError(
            _errors.E_INVALID_ARGUMENT,
            "image data must be bytes, bytearray or another buffer, not %s" % type(data).__name__,
        ) from None
    if view.nbytes < needed:
        raise InvalidArgumentError(
            _errors.E_INVALID_ARGUMENT,
            "buffer has %d bytes, a %dx%d image with stride %d needs %d"
            % (view.nbytes, width, height, stride, needed),
        )
    if isinstance(data, bytes) and not writable:
        keep = data
        address = ctypes.cast(ctypes.c_char_p(data), ctypes.c_void_p).value
    elif not view.readonly and view.c_contiguous:
        flat = view if (view.ndim == 1 and view.format == "B") else view.cast("B")
        keep = (ctypes.c_char * flat.nbytes).from_buffer(flat)
        address = ctypes.addressof(keep)
    elif writable:
        raise InvalidArgumentError(_errors.E_INVALID_ARGUMENT,
                                   "the image buffer must be writable (bytearray, memoryview)")
    else:
        keep = bytes(view)  # a read-only or strided buffer: one copy
        address = ctypes.cast(ctypes.c_char_p(keep), ctypes.c_void_p).value
    img = _native.Image(ctypes.sizeof(_native.Image), width, height, stride, fmt, address)
    return img, keep


Event = collections.namedtuple("Event", ["kind", "data"])
Event.__doc__ = """A session event: `kind` ("captured", "state_changed", ...) and `data`, the
JSON payload as a dict (keys "keyframes", "frames", "message", ...)."""


class _Handle:
    """An owned library handle: close() frees it (also at collection and on leaving a `with`);
    calls on a closed object raise StateError."""

    _what = "object"
    _h = None

    def close(self):
        raise NotImplementedError

    def __del__(self):
        try:
            self.close()
        except Exception:  # interpreter shutdown: the library may be gone already
            pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    @property
    def closed(self):
        return not self._h

    def _handle(self):
        if not self._h:
            raise StateError(_errors.E_STATE, "the %s is closed" % self._what)
        return self._h


class Calibration(_Handle):
    """The result of Context.calibrate_images(): `.result` (dict) and `.save(path)`."""

    _what = "calibration"

    def __init__(self, handle):
        self._h = handle

    def close(self):
        if self._h:
            _lib.posecal_calibration_destroy(self._h)
            self._h = None



    @property
    def result(self):
        h = self._handle()
        return _fetch_json(lambda b, n: _lib.posecal_calibration_json(h, b, n))

    def save(self, path):
        _check(_lib.posecal_calibration_save(self._handle(), _enc(path, "path")))


class Context(_Handle):
    """Camera backends shared by sessions (posecal_context). Thread-safe.

    backends: None for all, or a list of "sim", "images", "external", "aravis", "v4l2".
    """

    _what = "context"

    def __init__(self, backends=None):
        self._h = None
        # Open sessions (weakly: a forgotten session is still closed when it is collected),
        # closed before the context.
        self._sessions = weakref.WeakSet()
        self._sessions_lock = threading.Lock()
        opts = None if backends is None else {"backends": list(backends)}
        h = ctypes.c_void_p()
        _check(_lib.posecal_context_create(_options(opts), ctypes.byref(h)))
        self._h = h

    def close(self):
        """Closes every session still open on the context, then the context."""
        if self._h:
            with self._sessions_lock:
                sessions = list(self._sessions)
            for s in sessions:
                s.close()
            _lib.posecal_context_destroy(self._h)
            self._h = None




    def cameras(self):
        """Cameras of every enabled backend (list of dicts: uri, backend, id, vendor, ...)."""
        h = self._handle()
        return _fetch_json(lambda b, n: _lib.posecal_list_cameras(h, b, n))

    def features(self, uri):
        """The camera's settings: list of dicts (name, type, value, access, unit, range,
        options)."""
        h = self._handle()
        u = _enc(uri, "uri")
        return _fetch_json(lambda b, n: _lib.posecal_camera_features(h, u, b, n))

    def grab(self, uri, count, out_dir, timeout_ms=10000):
        """Saves `count` frames as PNG files in out_dir; returns the list of files and more."""
        h = self._handle()
        u, d = _enc(uri, "uri"), _enc(out_dir, "out_dir")
        return _fetch_json(
            lambda b, n: _lib.posecal_camera_grab(h, u, int(count), d, int(timeout_ms), b, n))

    def evaluate(self, result_path, uri, **options):
        """Test-set error of a calibration file on a camera (eps_test; eps_gt for sim://).
        options: target, frames, min_corners, timeout_ms."""
        h = self._handle()
        r, u, o = _enc(result_path, "result_path"), _enc(uri, "uri"), _options(options)
        return _fetch_json(lambda b, n: _lib.posecal_evaluate(h, r, u, o, b, n))

    def calibrate_images(self, images_dir, target=None, **options):
        """Offline calibration of a folder of images; returns a Calibration.
        options: fix_principal_point, fix_aspect_ratio, zero_tangential, fixed, min_corners."""
        h = ctypes.c_void_p()
        _check(_lib.posecal_calibrate_images(self._handle(), _enc(images_dir, "images_dir"),
                                             _enc(target, "target"), _options(options),
                                             ctypes.byref(h)))
        return Calibration(h)

    def open(self, uri, **config):
        """Opens a calibration session on a camera. config: the keys of posecal_session_open
        (core/session/session_keys.def): method, target, operator, convergence_threshold, max_keyframes,
        jaccard_threshold, still_motion_px, constraint_factor, target_timeout_frames,
        pose_candidates, lock_settings, max_tilt_deg, fixed, convergence_measure,
        measured_convergence, candidate_score, view_candidates, view_must_serve_target,
        board_timeout_s, accuracy_px, journal, journal_images, resume."""
        return Session(self, uri, **config)


def _queueing_callback(queue):
    def on_event(_user, kind, payload):
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

    def __init__(self, context, uri, **config):
        self._h = None
        self._context = context
        self._events = collections.deque()
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

    def close(self):
        if self._h:
            _lib.posecal_session_close(self._h)
            self._h = None
            with self._context._sessions_lock:
                self._context._sessions.discard(self)




    # ---- frames --------------------------------------------------------------------------
    def step(self, timeout_ms=1000):
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

    def feed(self, data, width, height, stride=None, format=PixelFormat.MONO8):
        """Processes a host frame: `data` is bytes, bytearray or a memoryview of 8-bit pixels
        (MONO8, BGR8 or RGB8), rows `stride` bytes apart (default: packed)."""
        img, keep = _image_view(data, width, height, stride, format, writable=False)
        _check(_lib.posecal_session_feed(self._handle(), ctypes.byref(img)))
        del keep

    def last_frame(self, format=PixelFormat.BGR8, with_overlay=False):
        """The last processed frame as (bytearray, width, height, stride), optionally with the
        guidance overlay drawn into it. Raises StateError before the first frame."""
        st = self.status
        if st.get("image_width") is None:
            raise StateError(_errors.E_STATE, "no frame processed yet")
        w, h = st["image_width"], st["image_height"]
        stride = w * PixelFormat.CHANNELS[format]
        buf = bytearray(stride * h)
        img, keep = _image_view(buf, w, h, stride, format, writable=True)
        _check(_lib.posecal_session_last_frame(self._handle(), ctypes.byref(img)))
        if with_overlay:
            _check(_lib.posecal_session_render_overlay(self._handle(), ctypes.byref(img)))
        del keep
        return buf, w, h, stride

    def render_overlay(self, data, width, height, stride=None, format=PixelFormat.BGR8):
        """Draws the guidance overlay into a writable host image (bytearray/memoryview)."""
        img, keep = _image_view(data, width, height, stride, format, writable=True)
        _check(_lib.posecal_session_render_overlay(self._handle(), ctypes.byref(img)))
        del keep

    def expected_error_map(self, width=40, height=23):
        """The predicted RMS projection error in pixels at width x height points from image edge
        to image edge (posecal_session_expected_error_map), as a list of `height` rows of
        `width` floats (NaN where the lens has no ray). Raises StateError before the second
        keyframe."""
        values = (ctypes.c_float * (width * height))()
        _check(_lib.posecal_session_expected_error_map(self._handle(), values, int(width),
                                                       int(height), 0))
        return [list(values[j * width:(j + 1) * width]) for j in range(height)]

    # ---- robot mode -----------------------------------------------------------------------
    def pose_reached(self):
        """Robot mode: the robot is at the current target."""
        _check(_lib.posecal_session_pose_reached(self._handle()))

    def skip_target(self):
        """Gives up on the current refinement target."""
        _check(_lib.posecal_session_skip_target(self._handle()))

    def interrupt(self):
        """Stops the calibration gracefully (any thread): no further frame is processed,
        status and result say "interrupted", and the calibration so far can be saved."""
        _check(_lib.posecal_session_interrupt(self._handle()))

    # ---- state ----------------------------------------------------------------------------
    @property
    def status(self):
        """The session's status (dict: state, keyframes, guidance, parameters, ...)."""
        h = self._handle()
        st = _fetch_json(lambda b, n: _lib.posecal_session_status(h, b, n))
        self._finished = bool(st.get("finished"))
        return st

    @property
    def finished(self):
        """True once the calibration has converged or failed."""
        if not self._finished and self._h:
            self.status  # noqa: B018 - refreshes _finished
        return self._finished

    @property
    def converged(self):
        return self.status["state"] == "converged"

    @property
    def result(self):
        """The current calibration (dict), or None before the second keyframe."""
        h = self._handle()
        try:
            return _fetch_json(lambda b, n: _lib.posecal_session_result(h, b, n))
        except StateError:
            return None

    @property
    def target_pose(self):
        """The board pose to reach as (rvec, tvec) in the camera frame (metres), or None when
        there is no target."""
        r = (ctypes.c_double * 3)()
        t = (ctypes.c_double * 3)()
        status = _lib.posecal_session_target_pose(self._handle(), r, t)
        if status == _errors.E_STATE:
            return None
        _check(status)
        return tuple(r), tuple(t)

    def save(self, path):
        """Saves the calibration (.yml/.yaml/.json). StateError before two keyframes."""
        _check(_lib.posecal_session_save(self._handle(), _enc(path, "path")))

    # ---- events ---------------------------------------------------------------------------
    def pending_events(self):
        """The events queued so far (and removes them from the queue)."""
        out = []
        while self._events:
            out.append(self._events.popleft())
        return out

    def events(self, timeout_ms=1000, max_frames=None):
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

    def __iter__(self):
        return self.events()

    def run(self, timeout_ms=1000, max_frames=None):
        """Steps until the calibration finishes; returns the result (None without one)."""
        for _ in self.events(timeout_ms, max_frames):
            pass
        return self.result
