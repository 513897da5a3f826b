#!/usr/bin/env bash
# Same-run before/after of `mortar build` (and `mortar sort`) on a seeded synthetic set:
#   bench/build_compare.sh BEFORE_DIR AFTER_DIR [POINTS] [REPS] [CPUS]
# BEFORE_DIR and AFTER_DIR hold a `mortar` binary each (AFTER_DIR also `mortar-gen`). Runs are
# interleaved (before, after, before, ...) so that machine noise hits both alike; CPUS (e.g.
# "0,1") pins every run with taskset. Prints one line per run (JSON fields of `--json`) and the
# medians of wall time and peak RSS per binary and input, and their ratio.
set -euo pipefail
before=$1
after=$2
points=${3:-20000000}
reps=${4:-3}
cpus=${5:-}
work=${WORK:-/tmp/mortar-build-compare}
mkdir -p "$work"
pin=()
if [ -n "$cpus" ]; then pin=(taskset -c "$cpus"); fi
for ext in las laz; do
  [ -f "$work/g.$ext" ] || "$after/mortar-gen" --points "$points" --seed 1 -o "$work/g.$ext" >/dev/null
done
results=$work/results.txt
: > "$results"
for r in $(seq 1 "$reps"); do
  for ext in las laz; do
    for which in before after; do
      bin=${!which}/mortar
      rm -rf "$work/store"
      j=$("${pin[@]}" "$bin" build "$work/g.$ext" -o "$work/store" --json 2>/dev/null)
      secs=$(printf '%s' "$j" | python3 -c 'import json,sys; j=json.load(sys.stdin); print(j["seconds"], j["peak_rss_bytes"], j["nodes_bytes"])')
      echo "build $ext $which run $r: $secs" | tee -a "$results"
      rm -rf "$work/store"
    done
  done
  for which in before after; do
    bin=${!which}/mortar
    t0=$(date +%s.%N)
    "${pin[@]}" "$bin" sort "$work/g.las" -o "$work/sorted.las" 2>/dev/null
    t1=$(date +%s.%N)
    echo "sort las $which run $r: $(python3 -c "print($t1 - $t0)") 0 0" | tee -a "$results"
    rm -f "$work/sorted.las"
  done
done
python3 - "$results" <<'PY'
import sys, statistics as st
rows = {}
for line in open(sys.argv[1]):
    head, vals = line.split(":")
    cmd, ext, which = head.split()[:3]
    s, rss, nb = vals.split()
    rows.setdefault((cmd, ext, which), []).append((float(s), int(rss), int(nb)))
print("| command | input | before s | after s | after/before | before RSS GB | after RSS GB | after/before |")
print("|---|---|---|---|---|---|---|---|")
for cmd, ext in sorted({(c, e) for c, e, _ in rows}):
    b, a = rows[(cmd, ext, "before")], rows[(cmd, ext, "after")]
    bs, as_ = st.median(x[0] for x in b), st.median(x[0] for x in a)
    br, ar = st.median(x[1] for x in b) / 1e9, st.median(x[1] for x in a) / 1e9
    rr = f"{ar / br:.3f}" if br else "-"
    print(f"| {cmd} | {ext} | {bs:.2f} | {as_:.2f} | {as_ / bs:.3f} | {br:.2f} | {ar:.2f} | {rr} |")
PY
