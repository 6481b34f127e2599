"""Complete calibrations through the Python binding: sim:// to convergence, host-fed frames,
robot mode, offline images (the example scripts: test_examples.py).

Run by ctest (plugin_python_calibration) with pytest, PYTHONPATH=plugin/python and
POSECAL_LIBRARY set.
"""
import os
import tempfile
import unittest

import numpy as np

import posecal


class Calibration(unittest.TestCase):
    def setUp(self):
        self.ctx = posecal.Context()
        self.tmp = tempfile.TemporaryDirectory()

    def tearDown(self):
        self.ctx.close()
        self.tmp.cleanup()

    def test_sim_calibration_converges(self):
        with self.ctx.open("sim://?seed=5") as s:
            events = list(s)  # steps until the calibration finishes
            kinds = [e.kind for e in events]
            self.assertIn("captured", kinds)
            self.assertIn("parameter_converged", kinds)
            last_state = [e.data for e in events if e.kind == "state_changed"][-1]
            self.assertEqual(last_state["to"], "converged")
            self.assertTrue(s.finished)
            self.assertTrue(s.converged)
            self.assertIsNone(s.target_pose)
            self.assertFalse(s.step())  # finished: nothing more to do
            r = s.result
            self.assertTrue(r["converged"])
            self.assertGreaterEqual(r["keyframes"], 5)
            for k in ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"):
                self.assertIsInstance(r[k], float)
                self.assertIsInstance(r["std"][k], float)
            self.assertLess(r["eps_test"], 0.2)
            self.assertLess(r["eps_gt"], 2.0)
            self.assertAlmostEqual(r["fx"], r["ground_truth"]["fx"], delta=5.0)
            yml = os.path.join(self.tmp.name, "cam.yml")
            s.save(yml)
            s.save(os.path.join(self.tmp.name, "cam.json"))
            frame = s.last_frame(with_overlay=True)
            self.assertEqual((frame.shape, frame.dtype), ((720, 1280, 3), np.uint8))
            np.testing.assert_array_equal(r.K, [[r["fx"], 0, r["cx"]], [0, r["fy"], r["cy"]],
                                                [0, 0, 1]])
            # The expected error: a figure in the status and the result, and its map.
            self.assertGreater(r["expected_error_px"], 0)
            self.assertIn(r["expected_error_limited_by"], r["covariance_order"])
            self.assertAlmostEqual(s.status["expected_error_px"], r["expected_error_px"], places=9)
            self.assertAlmostEqual(s.status["expected_error_p90_px"], r["expected_error_p90_px"], places=9)
            grid = s.expected_error_map()
            self.assertEqual((grid.shape, grid.dtype), ((23, 40), np.float32))
            rms = float(np.sqrt(np.mean(grid.astype(np.float64) ** 2)))
            self.assertEqual(s.expected_error_map(8, 5).shape, (5, 8))
            self.assertAlmostEqual(rms, r["expected_error_px"], delta=1e-5 * rms)
        # The saved file, evaluated on the same simulated camera, gives the session's errors.
        ev = self.ctx.evaluate(yml, "sim://?seed=5")
        self.assertEqual(ev["source"], "sim_test_set")
        self.assertAlmostEqual(ev["eps_gt"], r["eps_gt"], places=5)
        self.assertAlmostEqual(ev["eps_test"], r["eps_test"], places=5)

    def test_records(self):
        db = os.path.join(self.tmp.name, "records.sqlite")
        with self.ctx.open("sim://?seed=7", records=db, lens_id="C525-lens",
                           station_id="py-station") as s:
            list(s)
            run_id = s.result["run_id"]
            self.assertIsNone(s.result["records_note"])
        runs = posecal.records_list(db)
        self.assertEqual([r["run_id"] for r in runs], [run_id])
        self.assertEqual(runs[0]["state"], "converged")
        run = posecal.records_show(db, run_id[:8])
        self.assertEqual(run["lens_id"], "C525-lens")
        self.assertEqual(len(run["keyframes"]), run["result"]["keyframes"])
        solved = posecal.records_resolve(db, run_id)
        self.assertTrue(solved["identical"])
        self.assertEqual(solved["recomputed"], solved["stored"])
        yml = os.path.join(self.tmp.name, "exported.yml")
        posecal.records_export(db, run_id, yml)
        self.assertTrue(os.path.getsize(yml) > 0)
        with self.assertRaises(posecal.NotFoundError):
            posecal.records_show(db, "no-such-run")
        html = os.path.join(self.tmp.name, "report.html")
        report = posecal.records_report(html, db=db, run_id=run_id,
                                        pdf=os.path.join(self.tmp.name, "report.pdf"))
        self.assertEqual(report["plots"], ["coverage", "residuals", "distortion",
                                           "expected-error", "sigma", "fleet"])
        self.assertEqual(report["pages"], 7)
        with open(html, encoding="utf-8") as f:
            self.assertEqual(f.read().count('src="data:image/png;base64,'), 6)
        with self.assertRaises(posecal.InvalidArgumentError):
            posecal.records_report(html, db=db, run_id=run_id, result=yml)
        journal = os.path.join(self.tmp.name, "s8.journal")
        with self.ctx.open("sim://?seed=8", journal=journal) as s:
            list(s)
        imported = posecal.records_import(db, journal, station_id="py-station")
        self.assertEqual(imported["state"], "converged")
        self.assertTrue(posecal.records_resolve(db, imported["run_id"])["identical"])
        with self.assertRaises(posecal.FileError):
            posecal.records_list(os.path.join(self.tmp.name, "no", "dir", "r.sqlite"))

    def test_fed_frames_give_the_same_calibration(self):
        # A host feeding a simulated camera's frames into an "external" session gets exactly the
        # calibration of the simulated session: same frames, same engine. Formats, arrays and
        # buffer kinds vary frame by frame.
        cfg = {"target_timeout_frames": 36}  # what sim:// sessions use (docs/c-api.md)
        P = posecal.PixelFormat
        with self.ctx.open("sim://?seed=8", **cfg) as sim, self.ctx.open("external", **cfg) as ext:
            n = 0
            while sim.step():
                fmt = (P.MONO8, P.BGR8, P.RGB8)[n % 3]
                frame = sim.last_frame(fmt)
                h, w = frame.shape[:2]
                if n % 6 == 0:
                    ext.feed(frame)  # grey array
                elif n % 6 == 1:
                    ext.feed(frame[::-1].copy()[::-1])  # BGR, a reversed view (copied)
                elif n % 6 == 2:
                    ext.feed(frame, format=fmt)  # RGB array
                elif n % 6 == 3:
                    ext.feed(frame.tobytes(), w, h, format=fmt)  # the raw-buffer forms
                elif n % 6 == 4:
                    ext.feed(bytearray(frame.tobytes()), w, h, w * 3, fmt)
                else:
                    ext.feed(memoryview(frame.tobytes()), w, h, w * 3, fmt)
                n += 1
                self.assertLess(n, 2000)
            self.assertTrue(ext.finished)
            a, b = sim.status, ext.status
            self.assertTrue(b["converged"])
            self.assertEqual(a["keyframes"], b["keyframes"])
            for k in ("fx", "fy", "cx", "cy", "k1"):
                self.assertAlmostEqual(a["parameters"][k]["value"], b["parameters"][k]["value"],
                                       places=9)
            kinds = [e.kind for e in ext.pending_events()]
            self.assertIn("captured", kinds)

    def test_robot_session(self):
        # The robot side of the binding: target poses and pose_reached, up to the refinement.
        with self.ctx.open("sim://?seed=9&operator=robot") as s:
            targets = reached_ok = 0
            while s.step() and s.status["state"] != "refining":
                pose = s.target_pose
                if pose is None:
                    continue
                targets += 1
                rvec, tvec = pose
                self.assertEqual((len(rvec), len(tvec)), (3, 3))
                self.assertGreater(tvec[2], 0.05)  # in front of the camera
                try:
                    s.pose_reached()
                    reached_ok += 1
                except posecal.StateError:
                    pass
            self.assertEqual(s.status["state"], "refining")
            self.assertGreaterEqual(s.status["keyframes"], 2)
            self.assertIsNotNone(s.result)
            self.assertGreater(targets, 3)
            self.assertGreater(reached_ok, 3)
            with self.assertRaises(posecal.InvalidArgumentError):
                self.ctx.open("sim://?operator=robot", operator="person")
            s.skip_target()  # allowed while refining

    def test_calibrate_images(self):
        data = "/usr/share/doc/opencv-doc/examples/data"
        if not os.path.exists(os.path.join(data, "left01.jpg")):
            self.skipTest("opencv-doc is not installed")
        d = os.path.join(self.tmp.name, "left")
        os.makedirs(d)
        for name in sorted(os.listdir(data)):
            if name.startswith("left") and name.endswith(".jpg") and len(name) == 10:
                os.symlink(os.path.join(data, name), os.path.join(d, name))
        with self.ctx.calibrate_images(d, target="chessboard:9x6:0.025") as cal:
            r = cal.result
            self.assertIsInstance(r, posecal.Result)
            self.assertEqual((r.K.shape, r.D.shape, r.covariance.shape), ((3, 3), (5,), (9, 9)))
            self.assertEqual(r.K[0, 0], r["fx"])
            self.assertGreaterEqual(r["frames_used"], 10)
            self.assertLess(r["rms"], 0.5)
            cal.save(os.path.join(self.tmp.name, "left.yml"))
            # The other formats by name (docs/formats.md), read back as text.
            for fmt, name, key in (("ros", "left_ros.yaml", "distortion_model: plumb_bob"),
                                   ("mrcal", "left.cameramodel", "LENSMODEL_OPENCV5"),
                                   ("opencv", "left.json", '"camera_matrix"')):
                path = os.path.join(self.tmp.name, name)
                cal.save(path, format=fmt)
                with open(path) as f:
                    self.assertIn(key, f.read(), fmt)
            # A format that cannot hold the model (Kalibr's radtan has no k3) or none at all.
            for fmt in ("kalibr", "matlab"):
                with self.assertRaises(posecal.InvalidArgumentError):
                    cal.save(os.path.join(self.tmp.name, "x.yml"), format=fmt)
                self.assertFalse(os.path.exists(os.path.join(self.tmp.name, "x.yml")))
        ev = self.ctx.evaluate(os.path.join(self.tmp.name, "left.yml"), "images://" + d,
                               target="chessboard:9x6:0.025", frames=30)
        self.assertEqual(ev["source"], "camera")
        self.assertGreaterEqual(ev["test_frames"], 10)
        self.assertIsNone(ev["eps_gt"])
        self.assertLess(ev["eps_test"], 0.5)

    def test_calibrate_images_of_two_cameras(self):
        # A folder with both cameras of a stereo pair: refused naming the groups; camera_group
        # picks one, progress reports each of its images.
        data = "/usr/share/doc/opencv-doc/examples/data"
        if not os.path.exists(os.path.join(data, "right01.jpg")):
            self.skipTest("opencv-doc is not installed")
        d = os.path.join(self.tmp.name, "stereo")
        os.makedirs(d)
        for name in sorted(os.listdir(data)):
            if name.startswith(("left", "right")) and name.endswith(".jpg") and len(name) <= 11:
                os.symlink(os.path.join(data, name), os.path.join(d, name))
        with self.assertRaises(posecal.InvalidArgumentError) as e:
            self.ctx.calibrate_images(d, target="chessboard:9x6:0.025")
        self.assertIn("'left@640x480'", str(e.exception))
        self.assertIn("'right@640x480'", str(e.exception))
        seen = []
        with self.ctx.calibrate_images(d, target="chessboard:9x6:0.025", camera_group="right@640x480",
                                       progress=seen.append) as cal:
            r = cal.result
            self.assertEqual(r["camera_group"], "right@640x480")
            self.assertTrue(all(f.startswith("right") for f in r["used"]))
            self.assertTrue(any(x["file"].startswith("left") for x in r["rejected"]))
        self.assertEqual([p["index"] for p in seen], list(range(1, len(seen) + 1)))
        self.assertGreaterEqual(len(seen), 10)
        self.assertTrue(all(p["total"] == len(seen) and p["file"].startswith("right")
                            for p in seen))


if __name__ == "__main__":
    unittest.main()
