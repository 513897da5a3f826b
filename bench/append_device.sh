#!/usr/bin/env bash
# arrival.bin on the device (BENCHMARKS.md, "Append from the store's own points"): two binaries
# (BASE without arrival.bin, NEW with it; each a folder with mortar and mortar-gen):
#  1. interleaved builds of 100 M points of mortar-gen (default settings: the sorted engine),
#     both binaries, medians: what writing the ranks costs;
#  2. the sizes of nodes.bin and arrival.bin, and the GPU engine's store (arrival.bin too)
#     compared with the sorted engine's;
#  3. 20 M points more appended to the 100 M store, interleaved: from the store's own points
#     (arrival.bin; the original LAS moved away, else it is read), from the original inputs (the same store without arrival.bin), and the
#     build of both inputs from scratch; the appended stores compared with that build.
#   BASE=/tmp/ab/base NEW=/tmp/ab/new OUT=/tmp ROUNDS=3 bash bench/append_device.sh
set -u
base=$(cd "$BASE" && pwd); new=$(cd "$NEW" && pwd)
out=${OUT:-/tmp}; w=${WORK:-/tmp/append}; mkdir -p "$w"; cd "$w"
echo "machine: $(nproc) cpus, $(lscpu | grep -E '^(Thread|Core)' | tr -s ' ' | tr '\n' ';') $(nvidia-smi -L 2>/dev/null | head -1)"
[ -f g100.las ] || "$new/mortar-gen" --points 100000000 --seed 1 -o g100.las > /dev/null
[ -f g20.las ] || "$new/mortar-gen" --points 20000000 --seed 7 --origin 500500,5000200,0 --extent 1000 -o g20.las > /dev/null
t() { local t0=$(date +%s.%N); "$@" > /dev/null 2>&1 || echo "FAILED: $*"; python3 -c "print(round($(date +%s.%N) - $t0, 3))"; }
rm -rf s; "$new/mortar" build g100.las -o s -q
echo "SIZE nodes.bin $(stat -c %s s/nodes.bin) arrival.bin $(stat -c %s s/arrival.bin)"
rm -rf sg; "$new/mortar" build g100.las -o sg -q --engine gpu
for y in nodes.bin hierarchy.bin source.las arrival.bin; do cmp -s s/$y sg/$y && echo "EQ gpu-engine $y SAME" || echo "EQ gpu-engine $y DIFFERENT"; done
rm -rf sg so; cp -r s so; rm so/arrival.bin
for r in $(seq "${ROUNDS:-3}"); do
  rm -rf b; echo "R build-base $(t "$base/mortar" build g100.las -o b -q)"
  rm -rf b; echo "R build-new $(t "$new/mortar" build g100.las -o b -q)"
  # The original hidden: a store of LAS inputs that are there is appended from them.
  rm -rf a; cp -r s a; sync; mv g100.las g100.hidden
  echo "R append-own-points $(t "$new/mortar" build --append a g20.las -q)"; mv g100.hidden g100.las
  rm -rf ao; cp -r so ao; sync; echo "R append-originals $(t "$new/mortar" build --append ao g20.las -q)"
  rm -rf wb; echo "R build-both $(t "$new/mortar" build g100.las g20.las -o wb -q)"
done | tee "$out/append_rows.txt"
for y in nodes.bin hierarchy.bin source.las build.json arrival.bin; do
  cmp -s a/$y wb/$y && echo "EQ own-points $y SAME" || echo "EQ own-points $y DIFFERENT"
  [ $y = arrival.bin ] || { cmp -s ao/$y wb/$y && echo "EQ originals $y SAME" || echo "EQ originals $y DIFFERENT"; }
done
python3 - "$out/append_rows.txt" <<'PY'
import sys, statistics as st
rows = {}
for l in open(sys.argv[1]):
    p = l.split()
    if p and p[0] == 'R': rows.setdefault(p[1], []).append(float(p[2]))
for k, v in rows.items(): print(k, 'n=%d' % len(v), 'median %.3f' % st.median(v), 'all', v)
PY
rm -rf a ao b wb
