#!/usr/bin/env bash
# The payload coder before and after a change, on the device (BENCHMARKS.md, "A cheaper coder"):
# two binaries (BASE and NEW, each a folder with mortar, mortar-gen and codec_bench, the test
# binary of mortar-io), on 20 M and 100 M points of mortar-gen:
#  1. the stores of both binaries compared byte for byte (sorted and GPU engines);
#  2. the coder alone, one thread (codec_bench: every payload of the 20 M store coded again and
#     checked against the stored bytes), both binaries, 3 runs each;
#  3. interleaved rounds of `mortar build` (sorted and GPU engines, both binaries) and
#     PotreeConverter 2.1.2 -m random at 100 M, medians.
#   BASE=/tmp/cw/base NEW=/tmp/cw/new OUT=/tmp ROUNDS=3 bash bench/codec_device.sh
set -u
SIZES=${SIZES:-20 100}
potree=$(realpath "${POTREE:-.carry/potree/run}")
base=$(cd "$BASE" && pwd); new=$(cd "$NEW" && pwd)
out=${OUT:-/tmp}; w=${WORK:-/tmp/codec}; mkdir -p "$w"
echo "machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs); $(nvidia-smi -L 2>/dev/null | head -1)"
cd "$w"
for n in ${SIZES:-20 100}; do [ -f g$n.las ] || "$new/mortar-gen" --points ${n}000000 --seed 1 -o g$n.las > /dev/null; done
for f in $(for n in ${SIZES:-20 100}; do echo g$n.las; done); do
  for e in sorted gpu; do
    rm -rf a b; "$base/mortar" build $f -o a -q --engine $e; "$new/mortar" build $f -o b -q --engine $e
    d=0; for y in nodes.bin hierarchy.bin source.las; do cmp -s a/$y b/$y || d=1; done
    echo "EQ $f $e $([ $d = 0 ] && echo SAME || echo DIFFERENT)"
  done
done
rm -rf a b; "$base/mortar" build g${SIZES%% *}.las -o cs -q --engine sorted
for r in $(seq "${CODER_ROUNDS:-3}"); do for b in base new; do
  bin=$base; [ $b = new ] && bin=$new
  echo "CODER $b $(MORTAR_CODEC_BENCH=$w/cs "$bin/codec_bench" codec_bench --ignored --nocapture 2>&1 | grep -E 'codec_bench:|panicked')"
done; done
rm -rf cs
row() { # row <file> <tag> <binary> <engine>
  rm -rf s
  j=$("$3" build $1 -o s -q --json --engine $4 | tr -d '\n ')
  echo "R $1 $2 $(python3 -c "import json,sys; j=json.loads(sys.argv[1]); print(j['seconds'], j['read_seconds'], j['sort_seconds'], j['tree_seconds'], j['write_seconds'], j['peak_rss_bytes']/1e9)" "$j")"
}
for round in $(seq 1 "${ROUNDS:-3}"); do
  for f in $(for n in ${SIZES:-20 100}; do echo g$n.las; done); do
    for e in sorted gpu; do row $f $e-base "$base/mortar" $e; row $f $e-new "$new/mortar" $e; done
    if [ $f = g${SIZES##* }.las ]; then rm -rf pc; t0=$(date +%s.%N); "$potree" $f -o pc -m random >/dev/null 2>&1; t1=$(date +%s.%N); echo "R $f potree-random $(python3 -c "print($t1 - $t0)") 0 0 0 0 0"; rm -rf pc; fi
  done
done | tee "$out/codec_rows.txt"
rm -rf s
python3 - "$out/codec_rows.txt" <<'PY'
import sys, statistics as st
rows={}
for l in open(sys.argv[1]):
    p=l.split()
    if p[0]=='R': rows.setdefault((p[1],p[2]),[]).append([float(x) for x in p[3:]])
for k in sorted(rows):
    v=rows[k]; m=[st.median(c) for c in zip(*v)]
    print(k, 'n=%d'%len(v), 'total %.3f read %.3f sort %.3f tree %.3f write %.3f rssGB %.2f'%tuple(m), 'all', [round(x[0],3) for x in v])
PY
