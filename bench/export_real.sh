#!/usr/bin/env bash
# The exports on a real set (a directory of LAS/LAZ tiles, merged), against copc_converter
# (which takes the directory) and PotreeConverter 2.1.2 (the files), interleaved REPS times.
#   bench/export_real.sh MORTAR_BIN_DIR COPC_CONVERTER POTREE_RUN DIR [REPS]
set -euo pipefail
bin=$(cd "$1" && pwd); copc=$2; potree=$3; dir=$(realpath "$4"); reps=${5:-3}
work=${WORK:-/tmp/mortar-export-real}; mkdir -p "$work"; cd "$work"
files=$(ls "$dir"/*.la[sz])
echo "machine: $(nproc) cores; input: $dir ($(echo $files | wc -w) files, $(du -sb "$dir" | cut -f1) B)"
run() { local label=$1 out=$2; shift 2; rm -rf "$out"
  /usr/bin/time -f "%e %M" -o time.txt "$@" >/dev/null 2>err.txt || { echo "$label failed: $(tail -2 err.txt)" >&2; return; }
  echo "$label: $(tail -1 time.txt) $(du -sb "$out" | cut -f1)" | tee -a results.txt; rm -rf "$out"; }
: > results.txt
for r in $(seq 1 "$reps"); do
  run mortar-copc out.copc.laz "$bin/mortar" export "$dir" -o out.copc.laz --quiet
  run copc_converter cc.copc.laz "$copc" "$dir" cc.copc.laz --progress plain
  run mortar-potree pot "$bin/mortar" export "$dir" -o pot --format potree --quiet
  # shellcheck disable=SC2086
  run potreeconverter pc "$potree" $files -o pc
done
python3 - <<'PY'
import statistics, collections
d = collections.defaultdict(list)
for l in open("results.txt"):
    k, v = l.split(":", 1); s, kb, b = v.split(); d[k].append((float(s), int(kb) * 1024, int(b)))
med = {k: (statistics.median(x[0] for x in v), max(x[1] for x in v), v[0][2]) for k, v in d.items()}
for k, (s, rss, b) in sorted(med.items()):
    print(f"{k:16s} median {s:6.2f} s  peak RSS {rss/1e9:5.2f} GB  output {b/1e6:7.1f} MB")
for ours, peer in [("mortar-copc", "copc_converter"), ("mortar-potree", "potreeconverter")]:
    if ours in med and peer in med:
        print(f"{peer} / {ours} = {med[peer][0]/med[ours][0]:.2f}x; size {med[ours][2]/med[peer][2]:.2f}x of the peer's")
PY
