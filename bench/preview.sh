#!/usr/bin/env bash
# Issue 6: the cost of `mortar build --preview` and the preview's frame rate.
# Builds the same synthetic input with and without the preview, interleaved, REPS times each,
# and prints the median build times, their ratio and the preview's frames per second.
# The preview is drawn off screen (--preview-offscreen: same store view and rasterizer as the
# window, paced to 60 frames per second), so that it runs on GPU machines without a display.
# Usage: [ENGINE=gpu] [SIZE=1920x1080] bench/preview.sh BIN_DIR POINTS REPS BACKEND(gpu|cpu) [las|laz]
# ENGINE (default: the default engine) is passed as --engine to both builds, SIZE as
# --preview-size.
set -euo pipefail
B=${1:-target/release}; N=${2:-20000000}; REPS=${3:-3}; BACKEND=${4:-gpu}; EXT=${5:-las}
EXTRA=(); [ -n "${ENGINE:-}" ] && EXTRA+=(--engine "$ENGINE")
SIZE_ARGS=(); [ -n "${SIZE:-}" ] && SIZE_ARGS+=(--preview-size "$SIZE")
D=${TMPDIR:-/tmp}/mortar-preview-bench; mkdir -p "$D"
IN=$D/s$N.$EXT
[ -f "$IN" ] || "$B/mortar-gen" --points "$N" --seed 1 -o "$IN" 2>/dev/null
for r in $(seq "$REPS"); do
  rm -rf "$D/st"; "$B/mortar" build "$IN" -o "$D/st" "${EXTRA[@]}" --json > "$D/plain-$r.json"
  rm -rf "$D/st"; "$B/mortar" build "$IN" -o "$D/st" "${EXTRA[@]}" --json --preview --preview-offscreen --preview-backend "$BACKEND" "${SIZE_ARGS[@]}" > "$D/preview-$r.json"
done
python3 - "$D" "$REPS" <<'PY'
import json, statistics, sys
d, reps = sys.argv[1], int(sys.argv[2])
plain = [json.load(open(f"{d}/plain-{r}.json")) for r in range(1, reps + 1)]
prev = [json.load(open(f"{d}/preview-{r}.json")) for r in range(1, reps + 1)]
ps = statistics.median(j["seconds"] for j in plain)
vs = statistics.median(j["seconds"] for j in prev)
fps = statistics.median(j["preview"]["frames_per_second_during_build"] for j in prev)
med = statistics.median(j["preview"]["frame_ms_median"] for j in prev)
p95 = statistics.median(j["preview"]["frame_ms_p95"] for j in prev)
first = statistics.median(j["preview"]["frames"][0]["at_seconds"] for j in prev)
late = [j["preview"].get("frames_over_period") for j in prev]
up = statistics.median(max(f["nodes_uploaded"] for f in j["preview"]["frames"]) for j in prev)
print(f"points {plain[0]['points']}, renderer {prev[0]['preview']['renderer']}")
print(f"build without preview: median {ps:.2f} s {[round(j['seconds'], 2) for j in plain]} commits {plain[0]['commits']}")
print(f"build with preview:    median {vs:.2f} s {[round(j['seconds'], 2) for j in prev]} commits {prev[0]['commits']}")
print(f"throughput kept: {ps / vs * 100:.1f} %")
print(f"preview: {fps:.1f} frames/s during the build, frame {med:.2f} ms median, {p95:.2f} ms p95, first frame at {first * 1e3:.0f} ms")
print(f"frames over 16.7 ms: {late}; most nodes uploaded in one frame: {up}")
PY
