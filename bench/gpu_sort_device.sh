#!/usr/bin/env bash
# The GPU radix sort of the GPU engine on the device (BENCHMARKS.md, "The GPU sorts"): one binary
# (BIN holds mortar and mortar-gen), the GPU engine with its sort (MORTAR_GPU_SORT=1) against the same
# binary with the host's sort beside the GPU (MORTAR_GPU_SORT=0) and the sorted engine, and
# PotreeConverter 2.1.2 -m random, on 20 M and 100 M points of mortar-gen, interleaved rounds;
# then the stores of both GPU paths compared byte for byte with the sorted engine's (and the real
# files through bench/gpu_engine_device.sh with REAL=1 when EQ=1).
#   BIN=.carry/gs OUT=/tmp ROUNDS=4 EQ=1 bash bench/gpu_sort_device.sh
set -u
R=$(pwd); bin=$(cd "${BIN:-.carry/gs}" && pwd); potree=$(realpath "${POTREE:-.carry/potree/run}")
out=${OUT:-/tmp}; w=${WORK:-/tmp/gsort}; mkdir -p "$w"
echo "machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs); $(nvidia-smi -L 2>/dev/null | head -1)"
cd "$w"
for n in 20 100; do [ -f g$n.las ] || "$bin/mortar-gen" --points ${n}000000 --seed 1 -o g$n.las > /dev/null; done
row() { # row <file> <tag> <env> <engine>
  rm -rf s
  j=$(env $3 "$bin/mortar" build $1 -o s -q --json --engine $4 | tr -d '\n ')
  echo "R $1 $2 $(python3 -c "import json,sys; j=json.loads(sys.argv[1]); st=dict(j.get('gpu_steps') or []); print(j['seconds'], j['read_seconds'], j['sort_seconds'], j['tree_seconds'], j['write_seconds'], j['peak_rss_bytes'], st.get('sort',0), st.get('upload and sort',0))" "$j")"
}
# equality of the stores
for f in g20.las g100.las; do
  rm -rf a b c; "$bin/mortar" build $f -o a -q --engine sorted
  MORTAR_GPU_SORT=1 "$bin/mortar" build $f -o b -q --engine gpu
  MORTAR_GPU_SORT=0 "$bin/mortar" build $f -o c -q --engine gpu
  for x in b c; do d=0; for y in nodes.bin hierarchy.bin source.las; do cmp -s a/$y $x/$y || d=1; done; echo "EQ $f $x $([ $d = 0 ] && echo SAME || echo DIFFERENT)"; done
done 2>&1 | tee $out/gsort_eq.txt
rm -rf a b c s
for round in $(seq 1 "${ROUNDS:-4}"); do
  for f in g20.las g100.las; do
    row $f sorted MORTAR_GPU_SORT=1 sorted
    row $f gpu-gpusort MORTAR_GPU_SORT=1 gpu
    row $f gpu-hostsort MORTAR_GPU_SORT=0 gpu
    if [ $f = g100.las ]; then rm -rf pc; t0=$(date +%s.%N); "$potree" $f -o pc -m random >/dev/null 2>&1; t1=$(date +%s.%N); echo "R $f potree-random $(python3 -c "print($t1 - $t0)") 0 0 0 0 0 0 0"; rm -rf pc; fi
  done
done | tee $out/gsort_rows.txt
python3 - $out/gsort_rows.txt <<'PY'
import sys, statistics as st
rows={}
for l in open(sys.argv[1]):
    p=l.split()
    if p[0]=='R': rows.setdefault((p[1],p[2]),[]).append([float(x) for x in p[3:]])
for k in sorted(rows):
    v=rows[k]; m=[st.median(c) for c in zip(*v)]
    print(k, 'n=%d'%len(v), 'total %.3f read %.3f sort %.3f tree %.3f write %.3f rssGB %.2f gpu-sort %.3f upload+sort %.3f'%tuple(m), 'all', [round(x[0],3) for x in v])
PY
cd "$R"
[ "${EQ:-1}" = 1 ] && MORTAR_GPU_SORT=1 BIN=$bin REAL=1 GPU_MEMORY=4G FILES="g20.las" WORK=$w OUT=$out bash bench/gpu_engine_device.sh 0 | grep "^S "
