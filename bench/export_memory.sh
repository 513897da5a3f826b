#!/usr/bin/env bash
# Exports larger than --memory (issue 14): `mortar export` in memory against the same export
# through run files (--memory small enough to force the partitioned path), and copc_converter,
# interleaved REPS times on the same input. Wall seconds and peak RSS from /usr/bin/time.
#   bench/export_memory.sh MORTAR_BIN_DIR COPC_CONVERTER INPUT MEMORY [REPS] [FORMATS]
# FORMATS: "copc potree" (default) or one of them.
set -euo pipefail
bin=$(cd "$1" && pwd); copc=$2; in=$(realpath "$3"); memory=$4; reps=${5:-3}; formats=${6:-copc potree}
work=${WORK:-/tmp/mortar-export-memory}; mkdir -p "$work"; cd "$work"
echo "machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(free -g | awk '/Mem:/{print $2}') GiB"
echo "input: $in ($(stat -c %s "$in") B), partitioned with --memory $memory"
run() { # label, output, command...
  local label=$1 out=$2; shift 2
  rm -rf "$out"
  /usr/bin/time -f "%e %M" -o time.txt "$@" >/dev/null 2>err.txt || { echo "$label failed: $(tail -2 err.txt)" >&2; return; }
  echo "$label: $(tail -1 time.txt) $(du -sb "$out" | cut -f1)" | tee -a results.txt
  rm -rf "$out"
}
: > results.txt
for r in $(seq 1 "$reps"); do
  for f in $formats; do
    out=out.copc.laz; [ "$f" = potree ] && out=pot
    run "mortar-$f-memory" $out "$bin/mortar" export "$in" -o $out --format $f --memory 100G
    run "mortar-$f-partitioned" $out "$bin/mortar" export "$in" -o $out --format $f --memory "$memory"
  done
  case " $formats " in *" copc "*) run copc_converter cc.copc.laz "$copc" "$in" cc.copc.laz --progress plain ;; esac
done
python3 - <<'PY'
import statistics, collections
d = collections.defaultdict(list)
for l in open("results.txt"):
    k, v = l.split(":", 1)
    s, kb, b = v.split()
    d[k].append((float(s), int(kb) * 1024, int(b)))
med = {k: (statistics.median(x[0] for x in v), max(x[1] for x in v), v[0][2]) for k, v in d.items()}
for k, (s, rss, b) in sorted(med.items()):
    print(f"{k:26s} median {s:7.2f} s  peak RSS {rss/1e9:5.2f} GB  output {b/1e6:8.1f} MB  ({len(d[k])} runs)")
for f in ["copc", "potree"]:
    a, b = med.get(f"mortar-{f}-memory"), med.get(f"mortar-{f}-partitioned")
    if a and b:
        print(f"{f}: partitioned / in memory = {b[0]/a[0]:.2f}x the time, {b[1]/a[1]:.2f}x the peak RSS")
    c = med.get("copc_converter")
    if f == "copc" and b and c:
        print(f"copc: copc_converter / partitioned = {c[0]/b[0]:.2f}x faster, peak RSS {b[1]/c[1]:.2f}x of copc_converter's")
PY
