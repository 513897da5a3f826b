#!/usr/bin/env bash
# The distributed build (issue 15) on one machine: the same input planned into N jobs
# (N = 1, 2, 4, 8, 16 by default), the N jobs run at once with one thread each (N "nodes" of
# one core), then merged; against the one-machine build with every thread. Prints the wall
# seconds of the jobs and of the merge, the throughput against N times the one-job
# throughput (scaling efficiency), and checks that each merged store's hierarchy equals the
# one-machine store's in every entry but the payload offsets.
#   bench/distributed.sh MORTAR_BIN_DIR INPUT [NS] [MEMORY_PER_JOB]
set -euo pipefail
bin=$(cd "$1" && pwd); in=$(realpath "$2"); ns=${3:-1 2 4 8 16}; mem=${4:-4G}
work=${WORK:-/tmp/mortar-dist}; rm -rf "$work"; mkdir -p "$work"; cd "$work"
echo "machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(free -g | awk '/Mem:/{print $2}') GiB"
echo "input: $in ($(stat -c %s "$in") B)"
now() { date +%s.%N; }
t0=$(now); "$bin/mortar" build "$in" -o one --quiet; t1=$(now)
echo "one-machine build ($(nproc) threads): $(python3 -c "print(round($t1 - $t0, 2))") s"
python3 - <<'PY' > one.entries
import struct
h = open("one/hierarchy.bin", "rb").read(); n = struct.unpack_from("<Q", h, 24)[0]
for i in range(n):
    lvl, kind, x, y, z, _, cnt, off, ln = struct.unpack_from("<IIIIIIQQQ", h, 104 + 48 * i)
    print(lvl, kind, x, y, z, cnt, ln)
PY
for n in $ns; do
  rm -rf parts store; mkdir parts
  tp0=$(now); "$bin/mortar" plan "$in" --jobs "$n" -o plan.json --quiet; tp1=$(now)
  for ((i = 0; i < n; i++)); do
    "$bin/mortar" build --plan plan.json --job "$i" -o "parts/p$(printf %03d "$i")" --threads 1 --memory "$mem" --quiet --json > "parts/j$i.json" &
  done
  wait
  tj=$(now)
  "$bin/mortar" merge parts/p* -o store --quiet; tm=$(now)
  python3 - "$n" "$tp0" "$tp1" "$tj" "$tm" <<'PY'
import json, glob, struct, sys
n = int(sys.argv[1]); tp0, tp1, tj, tm = map(float, sys.argv[2:])
js = [json.load(open(f)) for f in glob.glob("parts/j*.json")]
pts = sum(j["points"] for j in js); slow = max(j["seconds"] for j in js)
h = open("store/hierarchy.bin", "rb").read(); m = struct.unpack_from("<Q", h, 24)[0]
mine = []
for i in range(m):
    lvl, kind, x, y, z, _, cnt, off, ln = struct.unpack_from("<IIIIIIQQQ", h, 104 + 48 * i)
    mine.append(f"{lvl} {kind} {x} {y} {z} {cnt} {ln}")
same = mine == open("one.entries").read().split("\n")[:-1]
jobs = tj - tp1
print(f"N={n:2d}: plan {tp1-tp0:6.2f} s, jobs {jobs:7.2f} s (slowest {slow:6.2f}, peak RSS {max(j['peak_rss_bytes'] for j in js)/1e9:.2f} GB), "
      f"merge {tm-tj:5.2f} s ({100*(tm-tj)/(tm-tp0):4.1f} % of the build), {pts/jobs/1e6:6.2f} M points/s, same entries as one machine: {same}")
open("scaling.txt", "a").write(f"{n} {pts/jobs}\n")
PY
done
python3 - <<'PY'
rows = [l.split() for l in open("scaling.txt")]
base = {int(n): float(t) for n, t in rows}.get(1)
for n, t in rows:
    if base:
        print(f"N={n}: {float(t)/base:5.2f}x the one-job throughput, efficiency {float(t)/base/int(n):.2f} (target 0.8)")
PY
