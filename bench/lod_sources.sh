#!/usr/bin/env bash
# Issue 30 §1: COPC files and EPT directories as LOD sources. For each input, `mortar render`
# at 1920x1080 (CPU rasterizer, default settings) of the framed view and of a closeup, with LOD
# (the default) and flat (--no-lod): seconds (median of REPS), nodes and bytes read.
#   bash bench/lod_sources.sh [BIN_DIR] [REPS]
# Inputs: a 20 M-point synthetic scan (mortar-gen, seed 1) exported to COPC by mortar (default
# settings), and the real EPT directory of ../shared/data (PyForestScan, 14.1 M points, 290 nodes).
set -euo pipefail
B=${1:-target/release}; REPS=${2:-3}
D=${TMPDIR:-/tmp}/mortar-lod-sources; mkdir -p "$D"
DATA=${MORTAR_TEST_DATA:-../shared/data}
[ -f "$D/g20.las" ] || "$B/mortar-gen" --points 20000000 --seed 1 -o "$D/g20.las" >/dev/null 2>&1
[ -f "$D/g20.copc.laz" ] || "$B/mortar" export "$D/g20.las" -o "$D/g20.copc.laz" -q
EPT=$DATA/PyForestScan/example_data/ept
run() { # run NAME INPUT ARGS...: prints the median seconds and what was read
  local name=$1 input=$2; shift 2
  local times=()
  for r in $(seq "$REPS"); do
    local t0=$(date +%s.%N)
    "$B/mortar" render "$input" -o "$D/out.png" --width 1920 --height 1080 --backend cpu --json "$@" > "$D/out.json" 2>/dev/null
    times+=("$(echo "$(date +%s.%N) - $t0" | bc)")
  done
  python3 - "$name" "$D/out.json" "${times[@]}" <<'PY'
import json, statistics, sys
name, j = sys.argv[1], json.load(open(sys.argv[2]))
t = sorted(float(x) for x in sys.argv[3:])
s = j.get("lod_source")
read = f"{s['nodes_read']}/{s['nodes']} nodes, {s['bytes_read'] / 1e6:.1f} of {s['bytes'] / 1e6:.1f} MB ({100 * s['bytes_read'] / s['bytes']:.1f} %), {s['points_read']} points" if s else f"flat, {j['points']} points"
print(f"{name:<28} median {statistics.median(t):.2f} s {[round(x, 2) for x in t]}  {read}, {j['points_drawn']} drawn")
PY
}
echo "machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs)"
C="--target 500100,5000100,0 --eye 500100,5000040,60"
run "copc 20M framed"        "$D/g20.copc.laz"
run "copc 20M framed flat"   "$D/g20.copc.laz" --no-lod
run "copc 20M closeup"       "$D/g20.copc.laz" $C
run "copc 20M closeup flat"  "$D/g20.copc.laz" $C --no-lod
E="--target 202150,2184150,1300 --eye 202150,2183950,1700 --fov 15"
run "ept 14M framed"         "$EPT"
run "ept 14M framed flat"    "$EPT" --no-lod
run "ept 14M closeup"        "$EPT" $E
run "ept 14M closeup flat"   "$EPT" $E --no-lod
