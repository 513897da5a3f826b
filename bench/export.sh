#!/usr/bin/env bash
# The exports against their peers (issue 14), interleaved REPS times on the same inputs:
# `mortar export` to COPC against copc_converter, and to Potree 2.0 against PotreeConverter
# 2.1.2 (default poisson), from LAZ and from LAS. Wall seconds and peak RSS from
# /usr/bin/time, output sizes; medians and ratios printed at the end.
#   bench/export.sh MORTAR_BIN_DIR COPC_CONVERTER POTREE_RUN INPUT.las [INPUT.laz] [REPS]
# INPUT.laz defaults to INPUT.las compressed in the same order (laspy).
set -euo pipefail
bin=$(cd "$1" && pwd); copc=$2; potree=$3; las=$(realpath "$4"); laz=${5:-}; reps=${6:-3}
work=${WORK:-/tmp/mortar-export-bench}; mkdir -p "$work"; cd "$work"
echo "machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(free -g | awk '/Mem:/{print $2}') GiB"
if [ -z "$laz" ]; then
  laz="$work/$(basename "${las%.las}").laz"
  [ -f "$laz" ] || ${PYTHON:-python3} -c "import laspy,sys; laspy.read(sys.argv[1]).write(sys.argv[2])" "$las" "$laz"
fi
echo "inputs: $las ($(stat -c %s "$las") B), $laz ($(stat -c %s "$laz") B)"
run() { # label, output, command...
  local label=$1 out=$2; shift 2
  rm -rf "$out"
  /usr/bin/time -f "%e %M" -o time.txt "$@" >/dev/null 2>err.txt || { echo "$label failed: $(tail -2 err.txt)" >&2; return; }
  local bytes; bytes=$(du -sb "$out" | cut -f1)
  echo "$label: $(tail -1 time.txt) $bytes" | tee -a results.txt
  rm -rf "$out"
}
: > results.txt
for r in $(seq 1 "$reps"); do
  for src in laz las; do
    in=$las; [ $src = laz ] && in=$laz
    run "mortar-copc-$src" out.copc.laz "$bin/mortar" export "$in" -o out.copc.laz --memory 100G
    run "copc_converter-$src" cc.copc.laz "$copc" "$in" cc.copc.laz --progress plain
    run "mortar-potree-$src" pot "$bin/mortar" export "$in" -o pot --format potree --memory 100G
    run "potreeconverter-$src" pc "$potree" "$in" -o pc
  done
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
    print(f"{k:24s} median {s:7.2f} s  peak RSS {rss/1e9:5.2f} GB  output {b/1e6:8.1f} MB  ({len(d[k])} runs)")
for src in ["laz", "las"]:
    for ours, peer in [("mortar-copc", "copc_converter"), ("mortar-potree", "potreeconverter")]:
        a, b = med.get(f"{ours}-{src}"), med.get(f"{peer}-{src}")
        if a and b:
            print(f"{src}: {peer} / {ours} = {b[0]/a[0]:.2f}x faster; size {a[2]/b[2]:.2f}x of the peer's")
PY
