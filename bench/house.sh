#!/usr/bin/env bash
# Issue 16's benchmark check: the same work by the binary before the house move (OLD) and this
# one (NEW), alternating, in one run, so that the ratio is a same-run comparison. Prints one line
# per measure: the medians of OLD and NEW and NEW/OLD.
# Usage: OLD=path/to/old/mortar NEW=target/release/mortar bash bench/house.sh INPUT.las [REPEATS] [BACKENDS]
#   BACKENDS: "cpu" (default) or "cpu gpu" (the GPU rasterizer, e.g. on the device).
set -euo pipefail
IN=$1
N=${2:-5}
BACKENDS=${3:-cpu}
OLD=${OLD:?set OLD to the earlier mortar binary}
NEW=${NEW:-target/release/mortar}
T=${TMPDIR:-/tmp}/mortar-house.$$
mkdir -p "$T"
trap 'rm -rf "$T"' EXIT
PY=${PYTHON:-python3}
log="$T/log.jsonl"
# One batch file for the renders (made by NEW; both read the same format).
"$NEW" batch "$IN" -o "$T/in.mbat" --quiet
for i in $(seq 1 "$N"); do
  for who in OLD NEW; do
    bin=${!who}
    # batch: wall seconds of the whole command (read, sort, write).
    w=$("$PY" -c 'import subprocess, sys, time; t = time.time(); subprocess.run(sys.argv[1:], check=True); print(time.time() - t)' "$bin" batch "$IN" -o "$T/out-$who.mbat" --quiet)
    echo "{\"who\":\"$who\",\"measure\":\"batch_wall_s\",\"v\":$w}" >> "$log"
    for b in $BACKENDS; do
      "$bin" render "$T/in.mbat" -o "$T/$who-$b.png" --backend "$b" --width 1920 --height 1080 --json --quiet > "$T/r.json"
      "$PY" - "$who" "$b" "$T/r.json" >> "$log" <<'PYEOF'
import json, sys
who, b, path = sys.argv[1:]
j = json.load(open(path))
print(json.dumps({"who": who, "measure": f"render_{b}_raster_s", "v": j["raster_seconds"]}))
g = j.get("gpu") or {}
if g.get("draw_ms") is not None:
    print(json.dumps({"who": who, "measure": f"render_{b}_gpu_draw_ms", "v": g["draw_ms"]}))
    print(json.dumps({"who": who, "measure": f"render_{b}_gpu_frame_s", "v": g["frame_seconds"]}))
PYEOF
    done
  done
done
for b in $BACKENDS; do
  cmp -s "$T/OLD-$b.png" "$T/NEW-$b.png" && echo "render $b: identical PNGs" || echo "render $b: PNGs DIFFER"
done
"$PY" - "$log" <<'PYEOF'
import json, sys, statistics
rows = [json.loads(l) for l in open(sys.argv[1])]
for m in dict.fromkeys(r["measure"] for r in rows):
    o = statistics.median(r["v"] for r in rows if r["measure"] == m and r["who"] == "OLD")
    n = statistics.median(r["v"] for r in rows if r["measure"] == m and r["who"] == "NEW")
    print(f"{m:28s} old {o:10.4f}  new {n:10.4f}  new/old {n / o:.3f}")
PYEOF
