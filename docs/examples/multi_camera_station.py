#!/usr/bin/env python3
"""Calibration station for several cameras: calibrates them at once, one thread per camera, and
writes one result file per camera plus a summary (station.py is the one-camera start).

    python3 multi_camera_station.py \
        --cameras "sim://?seed=1,sim://?seed=2" --out-dir results [--json]

Each thread opens its own posecal Session on one shared Context (the context is thread-safe,
a session is used by one thread); the library releases the GIL while it works, so the cameras
really are calibrated concurrently. Exit code: 0 all converged, 3 some did not converge,
2 some failed.
"""
import argparse
import json
import os
import re
import sys
import threading
import time

import posecal


def file_name(camera_id, taken):
    """The camera's identity as a file name, unique within this run."""
    base = re.sub(r"[^A-Za-z0-9._-]", "_", camera_id).lstrip(".") or "camera"
    name, i = base, 2
    while name in taken:
        name, i = "%s-%d" % (base, i), i + 1
    taken.add(name)
    return name


def calibrate(ctx, uri, out_dir, outcome, lock, taken, max_seconds, epoch):
    t0 = time.monotonic()
    outcome.update(uri=uri, converged=False, error=None, started_s=t0 - epoch)
    try:
        with ctx.open(uri) as session:
            camera = session.status["camera"]
            outcome["camera"] = camera
            for event in session.events(timeout_ms=2000):
                if event.kind == "captured":
                    print("%s: keyframe %d" % (uri, event.data["keyframes"]), file=sys.stderr)
                if time.monotonic() - t0 > max_seconds:
                    break
            result = session.result
            if result is None:
                raise posecal.StateError(posecal.errors.E_STATE, "fewer than two keyframes")
            with lock:
                name = file_name(camera["id"], taken)
            path = os.path.join(out_dir, name + ".yml")
            session.save(path)
            outcome.update(converged=result["converged"], keyframes=result["keyframes"],
                           eps_res=result["eps_res"], eps_test=result.get("eps_test"),
                           eps_gt=result.get("eps_gt"), file=path)
    except posecal.PosecalError as e:
        outcome.update(error=e.message, status=e.status_name)
    outcome["finished_s"] = time.monotonic() - epoch
    outcome["wall_s"] = time.monotonic() - t0


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cameras", default="sim://?seed=1,sim://?seed=2",
                    help="comma-separated camera URIs")
    ap.add_argument("--out-dir", required=True)
    ap.add_argument("--max-seconds", type=float, default=1800)
    ap.add_argument("--json", action="store_true", help="print the summary as JSON")
    args = ap.parse_args()
    uris = [u.strip() for u in args.cameras.split(",") if u.strip()]
    os.makedirs(args.out_dir, exist_ok=True)

    t0 = time.monotonic()
    outcomes = [dict() for _ in uris]
    lock, taken = threading.Lock(), set()
    with posecal.Context() as ctx:
        threads = [threading.Thread(target=calibrate,
                                    args=(ctx, uri, args.out_dir, o, lock, taken,
                                          args.max_seconds, t0))
                   for uri, o in zip(uris, outcomes)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()

    summary = {"cameras": outcomes, "total": len(outcomes),
               "converged": sum(1 for o in outcomes if o["converged"]),
               "wall_s": time.monotonic() - t0}
    with open(os.path.join(args.out_dir, "summary.json"), "w") as f:
        json.dump(summary, f, indent=2)
    if args.json:
        print(json.dumps(summary))
    else:
        for o in outcomes:
            if o["error"]:
                print("%-32s FAILED: %s" % (o["uri"], o["error"]))
            else:
                print("%-32s %s, %d keyframes, eps_res %.3f px -> %s"
                      % (o["uri"], "converged" if o["converged"] else "NOT converged",
                         o["keyframes"], o["eps_res"], o["file"]))
        print("%d of %d converged in %.1f s" % (summary["converged"], len(outcomes),
                                                summary["wall_s"]))
    if any(o["error"] for o in outcomes):
        return 2
    return 0 if summary["converged"] == len(outcomes) else 3


if __name__ == "__main__":
    sys.exit(main())
