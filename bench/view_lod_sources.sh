#!/usr/bin/env bash
# Issue 30 §1: `mortar view` on COPC files and EPT directories (nodes streamed in) against the
# same views of a store of the same points, and against `mortar render` of the same view.
# For each view, at 1920x1080 (BACKEND: cpu by default, gpu on a GPU machine): the time until the
# picture is complete (the screenshot frame, from the command's start), the frames that took,
# the median frame time of the last 10 of 30 frames (the steady frame rate once every node is
# drawn), and what was read. Needs Xvfb (DISPLAY is set to a private one).
#   [BACKEND=gpu] bash bench/view_lod_sources.sh [BIN_DIR] [REPS]
# Inputs: a 20 M-point synthetic scan (mortar-gen, seed 1) exported to COPC by mortar (default
# settings) and built into a store (default settings), and the real EPT directory of
# ../shared/data (PyForestScan, 14.1 M points, 290 nodes) when present.
set -euo pipefail
B=${1:-target/release}; REPS=${2:-3}; BACKEND=${BACKEND:-cpu}
D=${TMPDIR:-/tmp}/mortar-lod-sources; mkdir -p "$D"
DATA=${MORTAR_TEST_DATA:-../shared/data}
[ -f "$D/g20.las" ] || "$B/mortar-gen" --points 20000000 --seed 1 -o "$D/g20.las" >/dev/null 2>&1
[ -f "$D/g20.copc.laz" ] || "$B/mortar" export "$D/g20.las" -o "$D/g20.copc.laz" -q
[ -d "$D/g20.store" ] || "$B/mortar" build "$D/g20.las" -o "$D/g20.store" -q
EPT=$DATA/PyForestScan/example_data/ept
Xvfb :93 -screen 0 2048x1152x24 >/dev/null 2>&1 & XPID=$!
trap 'kill $XPID 2>/dev/null' EXIT
export DISPLAY=:93; sleep 1
view() { # view NAME INPUT ARGS...
  local name=$1 input=$2; shift 2
  local outs=()
  for r in $(seq "$REPS"); do
    "$B/mortar" view "$input" --width 1920 --height 1080 --backend "$BACKEND" --no-status \
      --screenshot "$D/view.png" --frames 30 --json "$@" > "$D/view-$r.json" 2>/dev/null
    outs+=("$D/view-$r.json")
  done
  "$B/mortar" render "$input" -o "$D/r.png" --width 1920 --height 1080 --backend "$BACKEND" "$@" >/dev/null 2>&1
  local t0=$(date +%s.%N)
  for r in $(seq "$REPS"); do
    "$B/mortar" render "$input" -o "$D/r.png" --width 1920 --height 1080 --backend "$BACKEND" "$@" >/dev/null 2>&1
  done
  local rt=$(echo "($(date +%s.%N) - $t0) / $REPS" | bc -l)
  python3 - "$name" "$rt" "${outs[@]}" <<'PY'
import json, statistics, sys
name, render_s, files = sys.argv[1], float(sys.argv[2]), sys.argv[3:]
js = [json.load(open(f)) for f in files]
def complete(j):
    # the first frame after which the content was not busy: the frames up to the last whose
    # points_drawn changed
    f = j["frames"]; last = max(i for i in range(len(f)) if f[i]["points_drawn"] == f[-1]["points_drawn"] and (i == 0 or f[i - 1]["points_drawn"] != f[i]["points_drawn"]))
    return f[last]["at_ms"] / 1e3, last + 1
done = statistics.median(complete(j)[0] for j in js)
frames = statistics.median(complete(j)[1] for j in js)
steady = statistics.median(statistics.median(fr["frame_ms"] for fr in j["frames"][-10:]) for j in js)
s = js[0].get("lod_source")
read = f"{s['nodes_read']}/{s['nodes']} nodes, {s['bytes_read'] / 1e6:.1f} of {s['bytes'] / 1e6:.1f} MB ({100 * s['bytes_read'] / s['bytes']:.1f} %)" if s else "store"
print(f"{name:<22} complete at {done:.2f} s ({frames:.0f} frames), steady frame {steady:.1f} ms, render {render_s:.2f} s; {read}; {js[0]['frames'][-1]['points_drawn']} drawn")
PY
}
echo "machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs); backend $BACKEND"
C="--target 500100,5000100,0 --eye 500100,5000040,60"
view "copc 20M framed"   "$D/g20.copc.laz"
view "store 20M framed"  "$D/g20.store"
view "copc 20M closeup"  "$D/g20.copc.laz" $C
view "store 20M closeup" "$D/g20.store" $C
if [ -d "$EPT" ]; then
  E="--target 202150,2184150,1300 --eye 202150,2183950,1700 --fov 15"
  view "ept 14M framed"  "$EPT"
  view "ept 14M closeup" "$EPT" $E
fi
