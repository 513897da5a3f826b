#!/usr/bin/env bash
# Issue 29 on the device, beyond bench/gpu_engine_device.sh: the GPU engine from LAZ against the
# bare parallel decode and the sorted engine (20 M points), and 1 B points within a tenth of the
# GPU memory their per-point GPU state needs, against the CPU engines, all in the same run.
#   BIN=.carry/bin bash bench/gpu_engine_scale.sh [laz|billion|all] [REPS]
# BIN holds mortar, mortar-gen and mortar-bench-decode; results go to ${OUT:-/tmp}/gpu_engine_scale.txt.
# POINTS (default 1000000000), GPU_MEMORY (default 1600M: a tenth of 16 bytes a point on the GPU at
# 1 B) and MEMORY (--memory of the builds that hold the input, default 110G) set the big case.
set -u
bin=$(cd "${BIN:-.carry/bin}" && pwd)
what=${1:-all}; reps=${2:-3}; out=${OUT:-/tmp}/gpu_engine_scale.txt
w=${WORK:-/tmp/gpus}; mkdir -p "$w"; cd "$w"
row() { # row <input> <name> <mortar build args...>: one timed build, its JSON summary in a line
  local f=$1 name=$2; shift 2
  rm -rf s
  local t0 t1 j
  t0=$(date +%s.%N)
  j=$(/usr/bin/time -f '%M' -o rss.txt "$bin/mortar" build "$f" -o s -q --json "$@" 2>err.txt | tr -d '\n ')
  t1=$(date +%s.%N)
  if [ -z "$j" ]; then echo "R $f $name FAILED $(head -c 300 err.txt)"; return; fi
  echo "R $f $name $(python3 -c "import json,sys; j=json.loads(sys.argv[1]); print(round($t1-$t0,3), j['seconds'], j['read_seconds'], j['tree_seconds'], j['sort_seconds'], j['write_seconds'], j['nodes_bytes'], int(open('rss.txt').read().split()[-1])*1024, j.get('engine'), json.dumps(j.get('gpu_steps', [])).replace(' ', ''), (j.get('gpu') or '-').replace(' ', '_'))" "$j")"
}
{
echo "machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(free -g | awk '/Mem:/{print $2}') GiB; $(nvidia-smi -L 2>/dev/null | head -1); disk free $(df -h . | awk 'NR==2{print $4}')"
if [ "$what" = laz ] || [ "$what" = all ]; then
  "$bin/mortar-gen" --points 20000000 --seed 1 -o g20.laz >/dev/null
  "$bin/mortar-gen" --points 20000000 --seed 1 -o g20.las >/dev/null
  rm -rf a b; "$bin/mortar" build g20.laz -o a -q --engine sorted; "$bin/mortar" build g20.laz -o b -q --engine gpu
  d=SAME; for x in nodes.bin hierarchy.bin source.las; do cmp -s a/$x b/$x || d=DIFFERENT; done; echo "S g20.laz $d"; rm -rf a b
  for r in $(seq 1 "$reps"); do
    for f in g20.laz g20.las; do
      row $f sorted --engine sorted
      row $f gpu --engine gpu
      echo "R $f decode $("$bin/mortar-bench-decode" $f | python3 -c 'import json,sys; print(json.load(sys.stdin)["seconds"])')"
    done
  done
  rm -f g20.laz g20.las
fi
if [ "$what" = billion ] || [ "$what" = all ]; then
  n=${POINTS:-1000000000}
  t0=$(date +%s.%N); "$bin/mortar-gen" --points "$n" --seed 1 -o big.las >/dev/null; t1=$(date +%s.%N)
  echo "generated $n points, $(stat -c %s big.las) bytes in $(python3 -c "print(round($t1-$t0,1))") s; disk free $(df -h . | awk 'NR==2{print $4}')"
  cat big.las > /dev/null
  row big.las gpu-within-${GPU_MEMORY:-1600M} --engine gpu --gpu-memory "${GPU_MEMORY:-1600M}" --memory "${MEMORY:-110G}"
  row big.las gpu --engine gpu --memory "${MEMORY:-110G}"
  row big.las sorted --engine sorted --memory "${MEMORY:-110G}"
  row big.las default
  rm -rf s
fi
} 2>&1 | tee "$out"
python3 - "$out" <<'PY'
import sys, json, statistics as st
rows = {}
for line in open(sys.argv[1]):
    p = line.split()
    if line.startswith("R ") and p[3] != "FAILED":
        rows.setdefault((p[1], p[2]), []).append(p[3:])
for (f, e), v in sorted(rows.items()):
    wall = st.median(float(x[0]) for x in v)
    if e == "decode":
        print(f"{f} decode: {wall:.2f} s (n={len(v)})"); continue
    med = lambda k: st.median(float(x[k]) for x in v)
    steps = {}
    for x in v:
        for name, s in json.loads(x[9]):
            steps.setdefault(name, []).append(s)
    sd = ", ".join(f"{k} {st.median(s):.3f}" for k, s in steps.items())
    print(f"{f} {e} [{v[0][8]}]: wall {wall:.2f} s, build {med(1):.2f}, read {med(2):.2f}, tree {med(3):.2f}, sort {med(4):.2f}, write {med(5):.2f}, store {int(med(6))} B, peak RSS {med(7)/1e9:.2f} GB (n={len(v)}); {sd}")
PY
