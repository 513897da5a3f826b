#!/bin/sh
# Progressive renderer (paper 000) on the CPU: convergence time, frame times and the budget
# reached, median of RUNS runs per configuration. Usage: bench/progressive.sh [RUNS] INPUT...
# Prints one JSON line per configuration (see BENCHMARKS.md).
set -e
RUNS=${RUNS:-3}
M=${MORTAR:-target/release/mortar}
OUT=${TMPDIR:-/tmp}/mortar-progressive-bench.png
VIEW="--width 1920 --height 1080"
for cfg in "--budget 1000000" "--budget 1000000 --pace" "--budget auto --target-ms 16.6 --pace" "--budget auto --target-ms 33 --pace" "--preload --budget 1000000" "--preload --progressive-all"; do
  for i in $(seq "$RUNS"); do
    case "$cfg" in
      *--progressive-all*) $M render "$@" $VIEW --preload --progressive 1 --budget 4294967295 -o "$OUT" --json ;;
      *) $M render "$@" $VIEW --progressive converge $cfg -o "$OUT" --json ;;
    esac
  done | python3 -c '
import json, sys, statistics as st
cfg = sys.argv[1]
runs = []
dec = json.JSONDecoder()
text = sys.stdin.read()
i = 0
while i < len(text):
    if text[i].isspace():
        i += 1
        continue
    j, i = dec.raw_decode(text, i)
    runs.append(j)
def med(f):
    v = [f(j) for j in runs]
    v = [x for x in v if x is not None]
    return round(st.median(v), 4) if v else None
during = lambda j: [f for f in j["frames"] if f["loaded"] < j["points"]]
after = lambda j: [f for f in j["frames"] if f["loaded"] == j["points"]]
print(json.dumps({
  "config": cfg, "runs": len(runs), "points": runs[0]["points"],
  "load_s": med(lambda j: j["load_seconds"]),
  "converge_s": med(lambda j: j["convergence_seconds"]),
  "converge_after_load_s": med(lambda j: j["convergence_seconds"] - j["load_seconds"]),
  "converge_frame": med(lambda j: j["convergence_frame"]),
  "frames_while_loading": med(lambda j: len(during(j))),
  "frame_ms_loading": med(lambda j: st.median([f["frame_ms"] for f in during(j)]) if during(j) else None),
  "frame_ms_loaded": med(lambda j: st.median([f["frame_ms"] for f in after(j)])),
  "reproject_ms": med(lambda j: st.median([f["reproject_ms"] for f in after(j)])),
  "fill_ms": med(lambda j: st.median([f["fill_ms"] for f in after(j)])),
  "prepare_ms": med(lambda j: st.median([f["prepare_ms"] for f in after(j)])),
  "budget_loaded": med(lambda j: st.median([f["filled"] for f in after(j)])),
  "visible": med(lambda j: j["pixels_covered"]),
}))' "$cfg"
done
# Baseline, same run: the brute-force `mortar render` (Morton sort into a temporary batch file,
# then one frame of every point).
for i in $(seq "$RUNS"); do
  s=$(date +%s.%N)
  $M render "$@" $VIEW --backend cpu -o "$OUT" --json > "$OUT.json"
  e=$(date +%s.%N)
  python3 -c 'import json,sys; j=json.load(open(sys.argv[1])); print(json.dumps({"wall_s": float(sys.argv[3]) - float(sys.argv[2]), "batch_s": j["batch_seconds"], "raster_s": j["raster_seconds"]}))' "$OUT.json" "$s" "$e"
done | python3 -c '
import json, sys, statistics as st
runs = [json.loads(l) for l in sys.stdin if l.strip()]
print(json.dumps({"config": "mortar render (batch file, brute force)", "runs": len(runs), **{k: round(st.median(r[k] for r in runs), 4) for k in runs[0]}}))'
