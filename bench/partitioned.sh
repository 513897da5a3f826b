#!/usr/bin/env bash
# The build engines on an input larger than the budget (issue 13): the sorted engine (no
# budget), the partitioned engine and the incremental engine under --memory MEM, on one seeded
# synthetic LAS set, interleaved REPS times; wall seconds and peak RSS from /usr/bin/time, and
# the partitioned build's phases from its --json.
#   bench/partitioned.sh BIN_DIR POINTS MEM [REPS]
set -euo pipefail
bin=$(cd "$1" && pwd); points=$2; mem=$3; reps=${4:-3}
work=${WORK:-/tmp/mortar-partitioned}; mkdir -p "$work"; cd "$work"
echo "machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(free -g | awk '/Mem:/{print $2}') GiB; $points points, --memory $mem"
[ -f "g$points.las" ] || "$bin/mortar-gen" --points "$points" --seed 1 -o "g$points.las" >/dev/null
run() { # label, args...
  local label=$1; shift
  rm -rf st
  /usr/bin/time -f "%e %M" -o time.txt "$bin/mortar" build "g$points.las" -o st --json "$@" > "$label.json" 2>/dev/null || echo "$label failed" >&2
  echo "$label: $(tail -1 time.txt) $(python3 -c "import json; j=json.load(open('$label.json')); print(j['engine'], 'read %.1f sort %.1f tree %.1f write %.1f commit %.1f' % (j['read_seconds'], j['sort_seconds'], j['tree_seconds'], j['write_seconds'], j['commit_seconds']))")" | tee -a results.txt
}
: > results.txt
for r in $(seq 1 "$reps"); do
  run sorted --engine sorted --memory 1T
  run partitioned --engine partitioned --memory "$mem"
  run incremental --engine incremental --memory "$mem"
done
rm -rf st
python3 - <<'PY'
import statistics, collections
d = collections.defaultdict(list)
for l in open("results.txt"):
    k, v = l.split(":", 1)
    s, kb = v.split()[:2]
    d[k].append((float(s), int(kb)))
for k, v in d.items():
    print(f"{k}: median {statistics.median(x for x, _ in v):.2f} s {[x for x, _ in v]}, peak RSS median {statistics.median(y for _, y in v) / 1e6:.2f} GB")
PY
