"""The Python binding's error handling and plumbing (fast: no full calibration).

Run by ctest (plugin_python_errors) with PYTHONPATH=plugin/python and POSECAL_LIBRARY set.
"""
import os
import subprocess
import sys
import tempfile
import unittest

import posecal
from posecal import errors


class Versions(unittest.TestCase):
    def test_versions(self):
        self.assertEqual(posecal.abi_version(), 1)
        self.assertRegex(posecal.version(), r"^\d+\.\d+\.\d+")
        self.assertTrue(os.path.exists(posecal.library_path), posecal.library_path)


class Errors(unittest.TestCase):
    def setUp(self):
        self.ctx = posecal.Context()
        self.tmp = tempfile.TemporaryDirectory()

    def tearDown(self):
        self.ctx.close()
        self.tmp.cleanup()

    def assertError(self, cls, status, fn, *args, **kwargs):
        with self.assertRaises(cls) as cm:
            fn(*args, **kwargs)
        e = cm.exception
        self.assertIsInstance(e, posecal.PosecalError)
        self.assertEqual(e.status, status)
        self.assertEqual(e.status_name, errors.STATUS_NAMES[status])
        self.assertTrue(e.message, "empty message")
        self.assertIn(e.status_name, str(e))
        return e

    def test_context_options(self):
        e = self.assertError(posecal.InvalidArgumentError, errors.E_INVALID_ARGUMENT,
                             posecal.Context, backends=["nope"])
        self.assertIn("nope", e.message)
        self.assertIsInstance(e, ValueError)  # InvalidArgumentError is also a ValueError
        with posecal.Context(backends=["sim"]) as only_sim:
            self.assertError(posecal.UnsupportedError, errors.E_UNSUPPORTED, only_sim.open,
                             "external")
            self.assertEqual([c["backend"] for c in only_sim.cameras()], ["sim"])

    def test_open_errors(self):
        self.assertError(posecal.InvalidArgumentError, errors.E_INVALID_ARGUMENT, self.ctx.open,
                         "nosuch://camera")
        e = self.assertError(posecal.InvalidArgumentError, errors.E_INVALID_ARGUMENT,
                             self.ctx.open, "sim://", bogus_key=1)
        self.assertIn("bogus_key", e.message)
        self.assertError(posecal.InvalidArgumentError, errors.E_INVALID_ARGUMENT, self.ctx.open,
                         "sim://", max_keyframes="many")
        self.assertError(posecal.InvalidArgumentError, errors.E_INVALID_ARGUMENT, self.ctx.open,
                         "sim://", target="charuco:1")
        for bad in (0, -0.1, float("nan"), float("inf"), "0.2"):
            self.assertError(posecal.InvalidArgumentError, errors.E_INVALID_ARGUMENT,
                             self.ctx.open, "sim://", accuracy_px=bad)
        self.assertError(posecal.NotFoundError, errors.E_NOT_FOUND, self.ctx.open,
                         "images:///nonexistent/posecal")
        self.assertError(posecal.InvalidArgumentError, errors.E_INVALID_ARGUMENT, self.ctx.open,
                         42)

    def test_wrong_state(self):
        with self.ctx.open("sim://?seed=2") as s:
            self.assertIsNone(s.result)  # no calibration before two keyframes
            self.assertIsNone(s.target_pose)
            self.assertError(posecal.StateError, errors.E_STATE, s.save,
                             os.path.join(self.tmp.name, "x.yml"))
            self.assertError(posecal.StateError, errors.E_STATE, s.pose_reached)  # person
            self.assertError(posecal.StateError, errors.E_STATE, s.last_frame)
            self.assertError(posecal.StateError, errors.E_STATE, s.expected_error_map)
            self.assertIsNone(s.status["expected_error_px"])
            self.assertIsNone(s.status["expected_error_p90_px"])
            self.assertTrue(s.step())
            self.assertFalse(s.finished)
            self.assertError(posecal.StateError, errors.E_STATE, s.skip_target)
            self.assertError(posecal.InvalidArgumentError, errors.E_INVALID_ARGUMENT, s.step, -1)
        self.assertTrue(s.closed)
        self.assertError(posecal.StateError, errors.E_STATE, s.step)

    def test_feed_checks_buffers(self):
        with self.ctx.open("external") as s:
            # The binding checks the buffer size (the library cannot check a raw pointer).
            e = self.assertError(posecal.InvalidArgumentError, errors.E_INVALID_ARGUMENT, s.feed,
                                 bytes(100), 20, 16)
            self.assertIn("needs 320", e.message)
            self.assertError(posecal.InvalidArgumentError, errors.E_INVALID_ARGUMENT, s.feed,
                             bytes(320), 20, 16, stride=19)
            self.assertError(posecal.InvalidArgumentError, errors.E_INVALID_ARGUMENT, s.feed,
                             bytes(320), 20, 16, format=9)
            self.assertError(posecal.InvalidArgumentError, errors.E_INVALID_ARGUMENT, s.feed,
                             bytes(320), 0, 16)
            self.assertError(posecal.InvalidArgumentError, errors.E_INVALID_ARGUMENT, s.feed,
                             "not pixels", 20, 16)
            self.assertError(posecal.StateError, errors.E_STATE, s.step)  # external: feed only
            s.feed(bytes(320), 20, 16)
            s.feed(bytearray(20 * 16 * 3), 20, 16, format=posecal.PixelFormat.RGB8)
            s.feed(memoryview(bytearray(24 * 16)), 20, 16, stride=24)
            # A frame of another size than the session's first frame: the library refuses.
            self.assertError(posecal.InvalidArgumentError, errors.E_INVALID_ARGUMENT, s.feed,
                             bytes(400), 20, 20)
            frame = s.last_frame(posecal.PixelFormat.MONO8)
            self.assertEqual((frame.shape, frame.strides), ((16, 20), (20, 1)))

    def test_camera_utilities(self):
        feats = self.ctx.features("sim://?seed=4")
        by_name = {f["name"]: f for f in feats}
        self.assertEqual(by_name["Width"]["value"], 1280)
        self.assertEqual(by_name["Operator"]["options"], ["person", "robot"])
        self.assertEqual(by_name["Width"]["access"], "read-only")
        self.assertError(posecal.NotFoundError, errors.E_NOT_FOUND, self.ctx.features,
                         "images:///nonexistent/posecal")
        out = os.path.join(self.tmp.name, "grab")
        g = self.ctx.grab("sim://?seed=4", 3, out, timeout_ms=20000)
        self.assertEqual(len(g["files"]), 3)
        for f in g["files"]:
            self.assertTrue(os.path.getsize(f["file"]) > 1000)
            self.assertEqual((f["width"], f["height"]), (1280, 720))
        self.assertError(posecal.InvalidArgumentError, errors.E_INVALID_ARGUMENT, self.ctx.grab,
                         "sim://", 0, out)
        e = self.assertError(posecal.NotFoundError, errors.E_NOT_FOUND, self.ctx.grab,
                             "images://" + out, 5, os.path.join(self.tmp.name, "regrab"))
        self.assertIn("3 of 5", e.message)
        self.assertError(posecal.TimeoutError, errors.E_TIMEOUT, self.ctx.grab, "external", 1,
                         out, timeout_ms=20)
        missing = os.path.join(self.tmp.name, "missing.yml")
        self.assertRaises(posecal.PosecalError, self.ctx.evaluate, missing, "sim://")
        self.assertError(posecal.InvalidArgumentError, errors.E_INVALID_ARGUMENT,
                         self.ctx.evaluate, missing, "sim://", bogus=1)
        board = os.path.join(self.tmp.name, "board.png")
        posecal.write_target(board, dpi=100)
        self.assertTrue(os.path.getsize(board) > 1000)
        a4 = os.path.join(self.tmp.name, "board_a4.pdf")
        posecal.write_target(a4, paper="a4")
        with open(a4, "rb") as f:
            self.assertEqual(f.read(5), b"%PDF-")
        self.assertError(posecal.InvalidArgumentError, errors.E_INVALID_ARGUMENT,
                         posecal.write_target, board, paper="a4")  # a paper size is PDF only
        self.assertError(posecal.InvalidArgumentError, errors.E_INVALID_ARGUMENT,
                         posecal.write_target, a4, paper="a5")
        self.assertError(posecal.InvalidArgumentError, errors.E_INVALID_ARGUMENT,
                         posecal.write_target, board, target="charuco:9x6")

    def test_context_close_closes_sessions(self):
        ctx = posecal.Context()
        s = ctx.open("sim://?seed=6")
        s.step()
        ctx.close()
        self.assertTrue(s.closed)
        self.assertError(posecal.StateError, errors.E_STATE, ctx.cameras)


class LibraryLookup(unittest.TestCase):
    def run_python(self, env, code):
        full_env = dict(os.environ)
        full_env.pop("POSECAL_LIBRARY", None)
        full_env.update(env)
        return subprocess.run([sys.executable, "-c", code], env=full_env, capture_output=True,
                              text=True, timeout=60)

    def test_explicit_library_that_does_not_exist(self):
        r = self.run_python({"POSECAL_LIBRARY": "/nonexistent/libposecal.so"}, "import posecal")
        self.assertNotEqual(r.returncode, 0)
        self.assertIn("POSECAL_LIBRARY", r.stderr)

    def test_system_loader(self):
        libdir = os.path.dirname(os.path.abspath(posecal.library_path))
        r = self.run_python({"LD_LIBRARY_PATH": libdir},
                            "import posecal; print(posecal.library_path, posecal.abi_version())")
        self.assertEqual(r.returncode, 0, r.stderr)
        self.assertIn("libposecal.so", r.stdout)
        self.assertTrue(r.stdout.strip().endswith(" 1"), r.stdout)


if __name__ == "__main__":
    unittest.main()
