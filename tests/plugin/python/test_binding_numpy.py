"""numpy arrays through the binding: feed() takes the image's size, channels and stride from the
array, last_frame() and render_overlay() return arrays, results give K, D and the covariance as
arrays; wrong dtypes and shapes are refused naming what was expected.

Run by ctest (plugin_python_numpy) with pytest.
"""
import json
import os
import warnings

import cv2
import numpy as np
import pytest

import posecal
from posecal import PixelFormat, errors

W, H = 1280, 720  # sim:// frames


@pytest.fixture(scope="module")
def frames():
    """One simulated frame (with the board in view) in the three formats."""
    with posecal.Context() as c, c.open("sim://?seed=3") as s:
        assert s.step()
        yield {
            "bgr": s.last_frame(),
            "grey": s.last_frame(PixelFormat.MONO8),
            "rgb": s.last_frame(PixelFormat.RGB8),
        }


@pytest.fixture
def ext(ctx):
    with ctx.open("external") as s:
        yield s


def fed_back(session, fmt=PixelFormat.BGR8):
    """What the library holds of the last frame fed, in `fmt`."""
    return session.last_frame(fmt)


# ---- arrays out --------------------------------------------------------------------------------
def test_last_frame_arrays(frames):
    bgr, grey, rgb = frames["bgr"], frames["grey"], frames["rgb"]
    assert isinstance(bgr, np.ndarray)
    assert (bgr.shape, bgr.dtype) == ((H, W, 3), np.uint8)
    assert (grey.shape, grey.dtype) == ((H, W), np.uint8)
    assert rgb.shape == (H, W, 3)
    for a in (bgr, grey, rgb):
        assert a.flags.c_contiguous and a.flags.writeable and a.flags.owndata
    np.testing.assert_array_equal(rgb, bgr[..., ::-1])
    # The simulated frame is a grey scene: the three channels are equal and are the grey image.
    np.testing.assert_array_equal(bgr[..., 1], grey)
    assert 20 < grey.mean() < 235 and grey.std() > 10  # a rendered board, not a blank buffer


def test_cv2_reads_and_writes_the_frames(frames, tmp_path):
    path = str(tmp_path / "frame.png")
    assert cv2.imwrite(path, frames["bgr"])
    np.testing.assert_array_equal(cv2.imread(path, cv2.IMREAD_COLOR), frames["bgr"])
    np.testing.assert_array_equal(cv2.cvtColor(frames["bgr"], cv2.COLOR_BGR2GRAY),
                                  frames["grey"])


def test_render_overlay_forms(ext, frames):
    ext.feed(frames["bgr"])
    plain = ext.last_frame()
    drawn = ext.render_overlay()  # a new array: the last frame with the overlay
    assert (drawn.shape, drawn.dtype) == ((H, W, 3), np.uint8)
    assert np.count_nonzero(np.any(drawn != plain, axis=2)) > 1000  # the guidance is drawn
    np.testing.assert_array_equal(ext.last_frame(with_overlay=True), drawn)
    # In place into the caller's array, which is returned.
    mine = plain.copy()
    assert ext.render_overlay(mine) is mine
    np.testing.assert_array_equal(mine, drawn)
    # A view the library cannot draw into in place (reversed rows): drawn through a copy.
    flipped = plain[::-1].copy()
    view = flipped[::-1]
    assert ext.render_overlay(view) is view
    np.testing.assert_array_equal(view, drawn)
    # RGB arrays with the keyword.
    rgb = plain[..., ::-1].copy()
    ext.render_overlay(rgb, format=PixelFormat.RGB8)
    np.testing.assert_array_equal(rgb, drawn[..., ::-1])
    # Read-only: refused (the overlay is drawn in place), naming the way out.
    ro = plain.copy()
    ro.flags.writeable = False
    with pytest.raises(ValueError, match="read-only"):
        ext.render_overlay(ro)
    # The raw-buffer form as before numpy: in place, returns None.
    buf = bytearray(plain.tobytes())
    assert ext.render_overlay(buf, W, H) is None
    assert bytes(buf) == drawn.tobytes()
    with pytest.raises(TypeError):
        ext.render_overlay(width=W, height=H)


def test_last_frame_buffer_is_the_deprecated_old_form(ext, frames):
    ext.feed(frames["grey"])
    with pytest.warns(DeprecationWarning, match="last_frame"):
        buf, w, h, stride = ext.last_frame_buffer(PixelFormat.MONO8)
    assert (type(buf), w, h, stride) == (bytearray, W, H, W)
    assert bytes(buf) == frames["grey"].tobytes()


# ---- arrays in ---------------------------------------------------------------------------------
@pytest.mark.parametrize("name,fmt", [("bgr", None), ("grey", None), ("rgb", PixelFormat.RGB8),
                                      ("bgr", PixelFormat.BGR8), ("grey", PixelFormat.MONO8)])
def test_feed_takes_the_layout_from_the_array(ext, frames, name, fmt):
    a = frames[name]
    if fmt is None:
        ext.feed(a)
    else:
        ext.feed(a, format=fmt)
    # The library holds exactly the pixels fed: it read the array as the format it is.
    np.testing.assert_array_equal(fed_back(ext), frames["bgr"])
    assert ext.status["frames"] == 1 and ext.status["image_width"] == W


def test_feed_grey_with_a_channel_axis(ext, frames):
    ext.feed(frames["grey"][:, :, None])  # H x W x 1, as some OpenCV calls return
    np.testing.assert_array_equal(fed_back(ext, PixelFormat.MONO8), frames["grey"])


def views(frames):
    """Array views of the simulated frame that are not C-contiguous, each with the image it
    shows."""
    bgr, grey = frames["bgr"], frames["grey"]
    wide = np.zeros((H, W + 64, 3), np.uint8)
    wide[:, 32:32 + W] = bgr
    return {
        "reversed rows": bgr[::-1],
        "mirrored": bgr[:, ::-1],
        "reversed channels": bgr[..., ::-1],
        "column slice of a wider image": wide[:, 32:32 + W],
        "every other row of a taller image": np.repeat(grey, 2, axis=0)[::2],
        "Fortran order": np.asfortranarray(grey),
        "every other column of a wider image": np.repeat(grey, 2, axis=1)[:, ::2],
        "channel planes": np.moveaxis(np.ascontiguousarray(np.moveaxis(bgr, 2, 0)), 0, 2),
        "broadcast grey": np.broadcast_to(grey[:1], (H, W)),
    }


@pytest.mark.parametrize("name", ["reversed rows", "mirrored", "reversed channels",
                                  "column slice of a wider image",
                                  "every other row of a taller image", "Fortran order",
                                  "every other column of a wider image", "channel planes",
                                  "broadcast grey"])
def test_feed_any_view(ext, frames, name):
    view = views(frames)[name]
    assert not view.flags.c_contiguous
    before = view.copy()
    ext.feed(view)
    fmt = PixelFormat.MONO8 if view.ndim == 2 else PixelFormat.BGR8
    np.testing.assert_array_equal(fed_back(ext, fmt), np.ascontiguousarray(view))
    np.testing.assert_array_equal(view, before)  # feeding never writes


def test_feed_read_only_arrays(ext, frames):
    ro = frames["bgr"].copy()
    ro.flags.writeable = False
    ext.feed(ro)
    np.testing.assert_array_equal(fed_back(ext), frames["bgr"])
    from_bytes = np.frombuffer(frames["grey"].tobytes(), np.uint8).reshape(H, W)
    assert not from_bytes.flags.writeable
    ext.feed(from_bytes)
    np.testing.assert_array_equal(fed_back(ext, PixelFormat.MONO8), frames["grey"])


def test_row_stride_is_passed_not_copied(ext, frames):
    # A column slice of a wider image has rows (W + 64) x 3 bytes apart: posecal_image can say
    # so, and the library reads it in place (same pixels as the contiguous frame).
    wide = np.zeros((H, W + 64, 3), np.uint8)
    wide[:, :W] = frames["bgr"]
    img = posecal._image.from_array(wide[:, :W], None, writable=False)
    assert img.image.stride_bytes == (W + 64) * 3
    assert img.image.data == wide.ctypes.data
    ext.feed(wide[:, :W])
    np.testing.assert_array_equal(fed_back(ext), frames["bgr"])


def test_old_buffer_forms_still_work(ext, frames):
    ext.feed(frames["grey"].tobytes(), W, H)
    ext.feed(bytearray(frames["bgr"].tobytes()), W, H, format=PixelFormat.BGR8)
    ext.feed(memoryview(frames["rgb"].tobytes()), W, H, W * 3, PixelFormat.RGB8)
    ext.feed(frames["grey"].reshape(-1), W, H)  # a flat uint8 array as a buffer
    np.testing.assert_array_equal(fed_back(ext), frames["bgr"])


# ---- what is refused ---------------------------------------------------------------------------
def check_refused(exc_info, *builtins):
    e = exc_info.value
    assert isinstance(e, posecal.InvalidArgumentError)
    assert e.status == errors.E_INVALID_ARGUMENT
    for b in builtins:
        assert isinstance(e, b)
    return str(e)


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.uint16, np.int8, np.bool_])
def test_wrong_dtype(ext, dtype):
    with pytest.raises(TypeError) as exc:
        ext.feed(np.zeros((H, W), dtype))
    msg = check_refused(exc, TypeError, ValueError)
    assert "uint8" in msg and np.dtype(dtype).name in msg
    with pytest.raises(TypeError, match="uint8"):
        ext.feed(np.zeros(W * H, dtype), W, H)  # also as a raw buffer
    assert ext.status["frames"] == 0


@pytest.mark.parametrize("shape", [(H, W, 4), (H, W, 2), (W * H,), (1, H, W, 3), (), (H, 0),
                                   (0, W, 3), (16, 70000)])
def test_wrong_shape(ext, shape):
    with pytest.raises(ValueError) as exc:
        ext.feed(np.zeros(shape, np.uint8))
    msg = check_refused(exc)
    assert str(shape) in msg or "1..65535" in msg
    if len(shape) not in (2, 3) or (len(shape) == 3 and shape[2] != 3):
        assert "H x W" in msg and "H x W x 3" in msg  # names what was expected
    assert ext.status["frames"] == 0


def test_format_must_match_the_array(ext, frames):
    with pytest.raises(ValueError, match="H x W x 3"):
        ext.feed(frames["grey"], format=PixelFormat.BGR8)
    with pytest.raises(ValueError, match="MONO8 needs an H x W array"):
        ext.feed(frames["bgr"], format=PixelFormat.MONO8)
    with pytest.raises(ValueError, match="unknown pixel format"):
        ext.feed(frames["bgr"], format=7)


def test_not_an_image(ext, frames):
    with pytest.raises(TypeError, match="numpy uint8 array") as exc:
        ext.feed([[0] * 32] * 32)
    check_refused(exc)
    with pytest.raises(TypeError, match="width and height"):
        ext.feed(frames["grey"].tobytes())  # a raw buffer has no shape
    with pytest.raises(TypeError, match="alone"):
        ext.feed(frames["grey"], stride=W)


def test_library_checks_still_apply(ext):
    ext.feed(np.zeros((32, 40), np.uint8))
    with pytest.raises(posecal.InvalidArgumentError):
        ext.feed(np.zeros((40, 32), np.uint8))  # another size than the session's frames
    with pytest.raises(ValueError):
        ext.feed(np.zeros((8, 8), np.uint8))  # smaller than 16 x 16


# ---- results as arrays -------------------------------------------------------------------------
def test_result_arrays(sim_result):
    r, path, frame = sim_result
    assert isinstance(r, dict) and isinstance(r, posecal.Result)
    K, D, cov = r.K, r.D, r.covariance
    assert (K.shape, K.dtype) == ((3, 3), np.float64)
    np.testing.assert_array_equal(K, [[r["fx"], 0, r["cx"]], [0, r["fy"], r["cy"]], [0, 0, 1]])
    assert r.distortion_names == ("k1", "k2", "p1", "p2", "k3")  # OpenCV's distCoeffs order
    assert (D.shape, D.dtype) == ((5,), np.float64)
    np.testing.assert_array_equal(D, [r[n] for n in r.distortion_names])
    assert r.parameter_names == ("fx", "fy", "cx", "cy") + r.distortion_names
    assert (cov.shape, cov.dtype) == ((9, 9), np.float64)
    np.testing.assert_allclose(cov, cov.T, rtol=1e-12, atol=0)
    np.testing.assert_allclose(np.sqrt(np.diag(cov)),
                               [r["std"][n] for n in r.parameter_names], rtol=1e-12)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    # Fresh arrays: changing one changes nothing.
    K[0, 0] = 0
    assert r.K[0, 0] == r["fx"]
    # The dict access is unchanged, and a Result is still JSON.
    assert r["converged"] is True and json.loads(json.dumps(r)) == dict(r)


def test_result_arrays_match_the_saved_file_and_opencv(sim_result):
    r, path, frame = sim_result
    fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
    np.testing.assert_allclose(fs.getNode("camera_matrix").mat(), r.K, rtol=1e-15)
    np.testing.assert_allclose(fs.getNode("distortion_coefficients").mat().ravel(), r.D,
                               rtol=1e-15)
    fs.release()
    # K and D go straight into OpenCV.
    und = cv2.undistort(frame, r.K, r.D)
    assert und.shape == frame.shape
    pts = cv2.undistortPoints(np.array([[[100.0, 80.0]]]), r.K, r.D, P=r.K)
    assert pts.shape == (1, 1, 2)


def test_session_result_none_before_two_keyframes(ctx):
    with ctx.open("sim://?seed=2") as s:
        assert s.result is None


def test_result_accessors_warn_nothing(sim_result):
    # A DeprecationWarning is only for the old tuple form of last_frame.
    r = sim_result[0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r.K, r.D, r.covariance  # noqa: B018


if __name__ == "__main__":
    raise SystemExit(pytest.main([os.path.abspath(__file__), "-v"]))
