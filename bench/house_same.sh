#!/usr/bin/env bash
# Issue 27's check: a redesign with no change of behaviour. Runs each command with the binary
# before the change (OLD) and this one (NEW), alternating, REPEATS times; compares every output
# byte for byte (files, stdout with the volatile timing fields removed, stderr) on the first
# round, then prints the median wall time of each and NEW/OLD (which binary runs first
# alternates by round: use an even REPEATS).
# Usage: OLD=path/to/old/mortar NEW=target/release/mortar bash bench/house_same.sh INPUT.las [REPEATS]
set -euo pipefail
IN=$(realpath "$1")
N=${2:-5}
OLD=$(realpath "${OLD:?set OLD to the earlier mortar binary}")
NEW=$(realpath "${NEW:-target/release/mortar}")
T=${TMPDIR:-/tmp}/mortar-house-same.$$
mkdir -p "$T"
trap 'rm -rf "$T"' EXIT
PY=${PYTHON:-python3}
head -c 50000 "$IN" > "$T/trunc.las"
"$NEW" batch "$IN" -o "$T/in.mbat" --quiet
"$NEW" build "$IN" -o "$T/in.store" --quiet
# name|arguments (OUT is the output path, a directory per binary and round)
cmds=(
  "sort|sort $IN -o OUT/s.laz --quiet"
  "batch|batch $IN -o OUT/b.mbat --quiet"
  "build|build $IN -o OUT/store --quiet --json"
  "build-partitioned|build $IN -o OUT/store --quiet --json --memory 64M"
  "export-copc|export $IN -o OUT/e.copc.laz --quiet --json"
  "export-potree|export $IN -o OUT/potree --format potree --quiet --json"
  "info|info $IN --json --stats"
  "render-cpu|render $T/in.mbat -o OUT/r.png --backend cpu --quiet"
  "render-lod|render $T/in.store -o OUT/l.png --backend cpu --quiet --json"
  "render-progressive|render $IN -o OUT/p.png --progressive converge --backend cpu --quiet"
  "bad-truncated|export $T/trunc.las -o OUT/t.copc.laz"
  "bad-missing|info $T/missing.laz"
)
# JSON fields that differ between any two runs (times, memory, paths)
scrub='import json, re, sys
t = sys.stdin.read()
try:
    j = json.loads(t)
except Exception:
    print(t.replace(sys.argv[1], "OUT"), end=""); sys.exit()
def clean(v):
    if isinstance(v, dict):
        return {k: clean(x) for k, x in v.items() if not re.search(r"seconds|per_second|peak_rss|_ms$", k)}
    if isinstance(v, list):
        return [clean(x) for x in v]
    if isinstance(v, str):
        return v.replace(sys.argv[1], "OUT")
    return v
print(json.dumps(clean(j), indent=1))'
log="$T/times.jsonl"
same=0; differ=0
for i in $(seq 1 "$N"); do
  for c in "${cmds[@]}"; do
    name=${c%%|*}; args=${c#*|}
    # Alternate which binary goes first: the second one runs while the first one's output is
    # still being written back by the kernel.
    order="OLD NEW"; [ $((i % 2)) = 0 ] && order="NEW OLD"
    for who in $order; do
      bin=${!who}; out="$T/$who-$i-$name"; mkdir -p "$out"
      a=${args//OUT/$out}
      s=$(date +%s.%N)
      set +e; $bin $a > "$out.stdout" 2> "$out.stderr"; rc=$?; set -e
      e=$(date +%s.%N)
      echo "{\"who\":\"$who\",\"measure\":\"$name\",\"v\":$(awk -v a="$s" -v b="$e" 'BEGIN{printf "%.4f", b - a}')}" >> "$log"
      echo "$rc" > "$out.rc"
      "$PY" -c "$scrub" "$out" < "$out.stdout" > "$out.stdout.clean"
      sed "s|$out|OUT|g" "$out.stderr" > "$out.stderr.clean"
    done
    if [ "$i" = 1 ]; then
      o="$T/OLD-1-$name"; n="$T/NEW-1-$name"
      if diff -r "$o" "$n" >/dev/null && cmp -s "$o.stdout.clean" "$n.stdout.clean" \
        && cmp -s "$o.stderr.clean" "$n.stderr.clean" && cmp -s "$o.rc" "$n.rc"; then
        echo "$name: identical (files $(find "$n" -type f | wc -l), exit $(cat "$n.rc"))"; same=$((same + 1))
      else
        echo "$name: DIFFERENT"; diff -r "$o" "$n" | head -5 || true
        diff "$o.stdout.clean" "$n.stdout.clean" | head -10 || true
        diff "$o.stderr.clean" "$n.stderr.clean" | head -10 || true
        differ=$((differ + 1))
      fi
    fi
    [ "$i" = 1 ] || rm -rf "$T"/*-"$i"-"$name"
  done
done
echo "outputs: $same identical, $differ different"
"$PY" - "$log" <<'PYEOF'
import json, sys, statistics
rows = [json.loads(l) for l in open(sys.argv[1])]
for m in dict.fromkeys(r["measure"] for r in rows):
    o = statistics.median(r["v"] for r in rows if r["measure"] == m and r["who"] == "OLD")
    n = statistics.median(r["v"] for r in rows if r["measure"] == m and r["who"] == "NEW")
    print(f"| {m} | {o:.3f} | {n:.3f} | {n / o:.3f} |")
PYEOF
