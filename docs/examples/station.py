#!/usr/bin/env python3
"""A first calibration station: frames go in as numpy arrays, K and D come out as numpy arrays.

    python3 station.py [camera.yml]

The frames come from posecal's simulated camera; a station with its own camera feeds that
camera's frames the same way (any H x W x 3 BGR or H x W grey uint8 array, such as
cv2.VideoCapture's) and shows `session.render_overlay()` to the person holding the board.
"""
import sys

import numpy as np

import posecal

out = sys.argv[1] if len(sys.argv) > 1 else "camera.yml"
# target_timeout_frames: give up a target pose after 36 frames, as sim:// sessions do, so the
# session keeps in step with the simulated person (who follows the sim:// session's guidance).
with posecal.Context() as ctx, ctx.open("sim://?seed=1") as camera, \
        ctx.open("external", target_timeout_frames=36) as session:
    said = None
    while not session.finished and camera.step():
        session.feed(camera.last_frame())  # an H x W x 3 uint8 array (BGR)
        guidance = session.status["guidance"]  # what to tell the person holding the board
        if guidance != said:
            print("guidance:", guidance)
            said = guidance
    result = session.result
    if result is None:  # the camera stopped before two keyframes
        sys.exit("no calibration")
    np.set_printoptions(precision=5, suppress=True)
    print("converged:", result["converged"], "with", result["keyframes"], "keyframes")
    print("K =", result.K, sep="\n")
    print("D =", result.D, "(%s)" % " ".join(result.distortion_names))
    session.save(out)
    print("saved", out)
