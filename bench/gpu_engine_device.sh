#!/usr/bin/env bash
# Issue 29 on the device (H200/H100, 16 cores): `--engine gpu` against `--engine sorted` (the
# default engine there) and PotreeConverter 2.1.2 -m random on the same generated inputs in the
# same run, with the GPU engine's steps; and the GPU's stores compared byte for byte with the
# sorted engine's on real files carried in DATA (several leaf capacities, merged tiles).
#   BIN=.carry/bin POTREE=.carry/potree/run DATA=.carry/data bash bench/gpu_engine_device.sh [REPS]
# BIN holds mortar and mortar-gen; results go to ${OUT:-/tmp}/gpu_engine_device.txt.
# REAL=0 skips the real files; FILES picks the generated inputs (default "g20.las g100.las");
# GPU_MEMORY=4G adds a GPU build within that much GPU memory (paged segments) to each rep.
set -u
bin=$(cd "${BIN:-.carry/bin}" && pwd); potree=$(realpath "${POTREE:-.carry/potree/run}")
data=$(cd "${DATA:-.carry/data}" && pwd)
reps=${1:-3}; out=${OUT:-/tmp}/gpu_engine_device.txt
w=${WORK:-/tmp/gpue}; mkdir -p "$w"; cd "$w"
same() { # same <tag> <args...>: builds with both engines, compares every file but build.json
  local tag=$1; shift
  rm -rf a b
  "$bin/mortar" build "$@" -o a -q --engine sorted 2>/dev/null; local ra=$?
  "$bin/mortar" build "$@" -o b -q --engine gpu 2>gpu.err; local rb=$?
  if [ $ra -ne 0 ] || [ $rb -ne 0 ]; then echo "S $tag both-failed-or-one: sorted=$ra gpu=$rb $(head -c 300 gpu.err)"; return; fi
  local d=0
  for x in nodes.bin hierarchy.bin source.las; do cmp -s a/$x b/$x || d=1; done
  [ $d = 0 ] && echo "S $tag SAME $(du -sb b | cut -f1)" || echo "S $tag DIFFERENT"
  rm -rf a b
}
{
echo "machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(free -g | awk '/Mem:/{print $2}') GiB; $(nvidia-smi -L 2>/dev/null | head -1)"
files=${FILES:-g20.las g100.las}
if [ "${REAL:-1}" = 1 ]; then
  for f in "$data"/*; do for cap in 50000 3000 200; do same "$(basename "$f")-cap$cap" "$f" --leaf-capacity $cap; done; done
  same "bcts-merged" "$data"/bcts_*.laz --leaf-capacity 2000
fi
for f in $files; do "$bin/mortar-gen" --points $(( ${f//[!0-9]/} * 1000000 )) --seed 1 -o $f >/dev/null; done
[ "${REAL:-1}" = 1 ] && same g20-default g20.las && same g20-cap3000 g20.las --leaf-capacity 3000
[ -n "${GPU_MEMORY:-}" ] && for f in $files; do same "$f-gpu-memory-$GPU_MEMORY" $f --gpu-memory "$GPU_MEMORY"; done
engines="sorted gpu"; [ -n "${GPU_MEMORY:-}" ] && engines="sorted gpu gpu-paged"
for r in $(seq 1 "$reps"); do
  for f in $files; do
    for e in $engines; do
      rm -rf s
      if [ $e = gpu-paged ]; then a="--engine gpu --gpu-memory $GPU_MEMORY"; else a="--engine $e"; fi
      j=$("$bin/mortar" build $f -o s -q --json $a | tr -d '\n ')
      echo "R $f $e $(python3 -c "import json,sys; j=json.loads(sys.argv[1]); print(j['seconds'], j['read_seconds'], j['tree_seconds'], j['sort_seconds'], j['write_seconds'], j['nodes_bytes'], j['peak_rss_bytes'], json.dumps(j.get('gpu_steps', [])).replace(' ', ''), (j.get('gpu') or '-').replace(' ', '_'))" "$j")"
    done
    rm -rf s
    rm -rf pc; t0=$(date +%s.%N); "$potree" $f -o pc -m random >/dev/null 2>&1; t1=$(date +%s.%N)
    echo "R $f potree-random $(python3 -c "print($t1 - $t0)") 0 0 0 0 0 0 [] -"; rm -rf pc
  done
done
} 2>&1 | tee "$out"
python3 - "$out" <<'PY'
import sys, json, statistics as st
rows = {}
for line in open(sys.argv[1]):
    if line.startswith("R "):
        p = line.split()
        rows.setdefault((p[1], p[2]), []).append(p[3:])
print("\n| input | sorted s | gpu s | sorted/gpu | PotreeConverter random s | random/gpu | gpu: read s | tree s (GPU stage) | place+leaf sort s | write s | GPU steps (median s) |")
print("|---|---|---|---|---|---|---|---|---|---|---|")
for f in sorted({k[0] for k in rows}, key=len):
    med = lambda e, k: st.median(float(x[k]) for x in rows[(f, e)])
    so, g, pr = med("sorted", 0), med("gpu", 0), med("potree-random", 0)
    steps = {}
    for x in rows[(f, "gpu")]:
        for name, s in json.loads(x[7]):
            steps.setdefault(name, []).append(s)
    sd = ", ".join(f"{k} {st.median(v):.3f}" for k, v in steps.items())
    if (f, "gpu-paged") in rows:
        print(f"gpu within --gpu-memory, {f}: {med('gpu-paged', 0):.2f} s (sorted/paged {so/med('gpu-paged', 0):.2f})")
    print(f"| {f} | {so:.2f} | {g:.2f} | {so/g:.2f} | {pr:.2f} | {pr/g:.2f} | {med('gpu',1):.2f} | {med('gpu',2):.2f} | {med('gpu',3):.2f} | {med('gpu',4):.2f} | {sd} | (n={len(rows[(f,'gpu')])})")
PY
