#!/usr/bin/env bash
# The GPU rasterizer benchmark of BENCHMARKS.md (issue 4): batches the four bcts strips of
# ../shared/data (2.83 M real points), then mortar-bench-gpu tiles them to 0.5-3 B points.
# Usage: bash bench/gpu.sh [DIR_WITH_bcts_*.laz] [OUT_DIR]   (release binaries in target/release
# or $BIN). On a machine without a loader, see the device notes for the Vulkan loader recipe.
set -euo pipefail
DATA=${1:-../shared/data/lasR/inst/extdata/bcts}
OUT=${2:-bench-data/gpu}
BIN=${BIN:-target/release}
mkdir -p "$OUT"
M="$OUT/bcts.mbat"
[ -f "$M" ] || "$BIN/mortar" batch "$DATA"/bcts_*.laz -o "$M"
run() { echo "== $*" >> "$OUT/bench.txt"; "$BIN/mortar-bench-gpu" "$M" "$@" >> "$OUT/bench.jsonl" 2>> "$OUT/bench.txt"; }
run --millions 500,1000,2000,3000 --frames 20 --compare-cpu --variants adaptive,brute
run --millions 500,1000 --frames 10 --atomics 32 --variants adaptive,brute
run --millions 500,1000 --frames 10 --width 960 --height 540 --variants adaptive,brute
run --millions 500,1000 --frames 10 --width 3840 --height 2160 --variants adaptive,brute
run --millions 20,100,500 --frames 5 --backend cpu --variants adaptive,brute
grep -v '^{' "$OUT/bench.txt"
