#!/usr/bin/env bash
# `mortar build --append` in place against the whole build (issue 29 item 4): a store of
# POINTS points of mortar-gen (seed 1, 1 km square), then a day's flight of NEW points inside it
# (seed 7, a 300 m square), appended ROUNDS times each way, interleaved, from a copy of the
# store: in place (the default), MORTAR_APPEND_REBUILD=1 (the whole build, reading the LAS
# originals), and the build of both files from scratch. Checks that the in-place store holds
# the whole build's tree (payload bytes, ranks, source header, build record).
# MEM, where set, is given as --memory to every build and append.
# Usage: BIN=target/release OUT=/tmp/x POINTS=10000000 NEW=100000 ROUNDS=3 [MEM=110G] bash bench/append_in_place.sh
set -euo pipefail
BIN=${BIN:-target/release}; OUT=${OUT:-/tmp/append-bench}; POINTS=${POINTS:-10000000}
NEW=${NEW:-100000}; ROUNDS=${ROUNDS:-3}
M=$(realpath "$BIN/mortar"); G=$(realpath "$BIN/mortar-gen"); HERE=$(cd "$(dirname "$0")" && pwd)
MEMF=(); [ -n "${MEM:-}" ] && MEMF=(--memory "$MEM")
mkdir -p "$OUT"; cd "$OUT"
[ -f big.las ] || "$G" --points "$POINTS" --seed 1 -o big.las > /dev/null
[ -f day.las ] || "$G" --points "$NEW" --seed 7 --extent 300 --origin 500300,5000300,0 -o day.las > /dev/null
rm -rf s0 whole; "$M" build big.las -o s0 -q "${MEMF[@]}"; "$M" build big.las day.las -o whole -q "${MEMF[@]}"
echo "store: $POINTS points, $(du -sb s0 | cut -f1) bytes; new: $NEW points; $(nproc) threads"
t() { local s=$(date +%s%N); "$@" > /dev/null; local e=$(date +%s%N); awk -v a="$s" -v b="$e" 'BEGIN { printf "%.3f", (b - a) / 1e9 }'; }
for r in $(seq 1 "$ROUNDS"); do
  rm -rf s s.append; cp -r s0 s; sync
  a=$(t "$M" build --append s day.las -q "${MEMF[@]}")
  rm -rf s s.append; cp -r s0 s; sync
  b=$(t env MORTAR_APPEND_REBUILD=1 "$M" build --append s day.las -q "${MEMF[@]}")
  rm -rf w; c=$(t "$M" build big.las day.las -o w -q "${MEMF[@]}")
  echo "round $r: in place $a s, whole append $b s, build of both $c s"
done
rm -rf s s.append; cp -r s0 s
"$M" build --append s day.las -q --json "${MEMF[@]}" | grep -E '"(kept_nodes|nodes|seconds|read_seconds|tree_seconds|write_seconds|peak_rss_bytes)"'
for f in source.las build.json arrival.bin; do cmp s/$f whole/$f; done
"$M" info s --json > /dev/null
echo "in place: same source.las, build.json, arrival.bin as the whole build"
if command -v python3 > /dev/null; then python3 "$HERE/same_tree.py" s whole; fi
