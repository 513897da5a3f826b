#!/usr/bin/env bash
# Same-run comparison of the build engines, the decode baseline, `mortar batch` and
# PotreeConverter 2.1.2 on one seeded synthetic set (issue 13):
#   bench/engine.sh BIN_DIR POTREE_DIR [POINTS] [REPS] [THREADS...]
# BIN_DIR holds mortar, mortar-gen and mortar-bench-decode; POTREE_DIR the PotreeConverter
# binary and its liblaszip.so (libtbb12 must be loadable; LD_LIBRARY_PATH is passed on).
# Runs are interleaved (every variant once per repetition) so that machine noise hits all
# alike; prints one line per run (wall seconds, peak RSS KB) and the medians. THREADS (e.g.
# "1 2 4 8 16") adds a thread-scaling table of `mortar build` (sorted engine, LAS and LAZ).
set -euo pipefail
bin=$(cd "$1" && pwd)
potree=$(cd "$2" && pwd)
points=${3:-20000000}
reps=${4:-3}
shift 4 || true
threads=("$@")
work=${WORK:-/tmp/mortar-engine}
mkdir -p "$work"
cd "$work"
echo "machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(free -g | awk '/Mem:/{print $2}') GiB"
for ext in las laz; do
  [ -f "g.$ext" ] || "$bin/mortar-gen" --points "$points" --seed 1 -o "g.$ext" >/dev/null
done
results=$work/results.txt
: > "$results"
timed() { # label, command...
  local label=$1
  shift
  /usr/bin/time -f "%e %M" -o "$work/time.txt" "$@" >/dev/null 2>&1 || echo "$label: failed" >&2
  echo "$label: $(tail -1 "$work/time.txt")" | tee -a "$results"
}
clean() { rm -rf st pc o.mbat; }
for r in $(seq 1 "$reps"); do
  for ext in las laz; do
    clean; timed "decode $ext" "$bin/mortar-bench-decode" "g.$ext"
    clean; timed "build-sorted $ext" "$bin/mortar" build "g.$ext" -o st --engine sorted
    clean; timed "build-incremental $ext" "$bin/mortar" build "g.$ext" -o st --engine incremental
    clean; timed "batch $ext" "$bin/mortar" batch "g.$ext" -o o.mbat
    clean; timed "potree-random $ext" "$potree/PotreeConverter" "g.$ext" -o pc -m random
    clean; timed "potree-poisson $ext" "$potree/PotreeConverter" "g.$ext" -o pc
  done
done
for t in "${threads[@]}"; do
  for r in $(seq 1 "$reps"); do
    for ext in las laz; do
      clean; timed "threads-$t build-sorted $ext" "$bin/mortar" --threads "$t" build "g.$ext" -o st --engine sorted
    done
  done
done
clean
python3 - "$results" "$points" <<'PY'
import sys, statistics as st
rows = {}
for line in open(sys.argv[1]):
    label, vals = line.rsplit(":", 1)
    v = vals.split()
    if len(v) != 2:
        continue
    rows.setdefault(label.strip(), []).append((float(v[0]), int(v[1])))
n = int(sys.argv[2])
med = {k: (st.median(x[0] for x in v), st.median(x[1] for x in v) / 1e6, len(v)) for k, v in rows.items()}
print("| run | median s | M points/s | peak RSS GB | runs | vs decode | sorted vs this |")
print("|---|---|---|---|---|---|---|")
for k in sorted(med):
    s, rss, c = med[k]
    ext = k.split()[-1]
    dec = med.get(f"decode {ext}", (None,))[0]
    srt = med.get(f"build-sorted {ext}", (None,))[0]
    vs_dec = f"{dec / s:.2f}x" if dec and not k.startswith("decode") else "-"
    vs_srt = f"{s / srt:.2f}x" if srt and not k.startswith(("decode", "build-sorted", "threads")) else "-"
    print(f"| {k} | {s:.2f} | {n / s / 1e6:.1f} | {rss:.2f} | {c} | {vs_dec} | {vs_srt} |")
PY
