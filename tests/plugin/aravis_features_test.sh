#!/bin/bash
# plugin_aravis_cli (fake-hw): `posecal features` and `posecal grab` on a GenICam camera through
# the Aravis backend, against Aravis' GigE Vision simulator (arv-fake-gv-camera-0.8) on loopback.
# Exit 77 (skipped) where the simulator is not installed or cannot listen.
#
# usage: aravis_features_test.sh POSECAL_CLI WORK_DIR
set -uo pipefail
cli=$1 work=$2
sim=$(command -v arv-fake-gv-camera-0.8) || { echo "arv-fake-gv-camera-0.8 not installed: skipped"; exit 77; }
rm -rf "$work" && mkdir -p "$work"
"$sim" -i 127.0.0.1 > "$work/simulator.log" 2>&1 &
sim_pid=$!
trap 'kill $sim_pid 2>/dev/null; wait $sim_pid 2>/dev/null' EXIT
uri=aravis://127.0.0.1
for _ in $(seq 50); do
  "$cli" features --camera $uri --json > "$work/features.json" 2> "$work/features.err" && break
  kill -0 $sim_pid 2>/dev/null || { echo "the simulator could not start: skipped"; cat "$work/simulator.log"; exit 77; }
  sleep 0.1
done
[ -s "$work/features.json" ] || { echo "no answer from the simulator"; cat "$work/features.err"; exit 1; }
python3 - "$work/features.json" <<'PY' || exit 1
import json, sys
feats = {f["name"]: f for f in json.load(open(sys.argv[1]))}
def expect(cond, what):
    if not cond:
        sys.exit("features: " + what)
expect(feats["DeviceVendorName"]["value"] == "Aravis", "vendor")
expect(feats["Width"]["type"] == "integer" and isinstance(feats["Width"]["value"], int), "Width")
expect(feats["Width"]["access"] == "read-write", "Width access")
expect(feats["Width"]["range"]["min"] >= 1 and feats["Width"]["range"]["max"] >= 512, "Width range")
expect("Mono8" in feats["PixelFormat"]["options"], "PixelFormat options")
expect(feats["AcquisitionStart"]["type"] == "command", "command type")
expect(any(f["type"] == "float" and isinstance(f["value"], float) for f in feats.values()), "a float")
print("%d features ok" % len(feats))
PY
"$cli" grab --camera $uri --count 3 --out "$work/frames" --timeout-ms 10000 --json > "$work/grab.json" || exit 1
python3 - "$work/grab.json" <<'PY' || exit 1
import json, os, sys
g = json.load(open(sys.argv[1]))
files = g["files"]
if len(files) != 3 or any(os.path.getsize(f["file"]) < 100 for f in files):
    sys.exit("grab: %r" % files)
if g["camera"]["backend"] != "aravis":
    sys.exit("grab: camera %r" % g["camera"])
print("grab ok: %dx%d" % (files[0]["width"], files[0]["height"]))
PY
