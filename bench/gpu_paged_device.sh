#!/bin/bash
# Paged GPU builds (issue 29 item 2): `mortar build --engine gpu --gpu-memory M` with the voxel
# passes walking the points in leaf order (NEW) against arrival order (BASE), same inputs, same
# machine, interleaved; the stores compared byte for byte.
#   BASE=dir NEW=dir [ROUNDS=3] [BIG=1] bash bench/gpu_paged_device.sh
# BASE and NEW hold mortar and mortar-gen. 100 M points of `mortar-gen --seed 1` within 160M of
# GPU memory (ROUNDS rounds), then with BIG=1 1 B points (34 GB LAS) within 1600M, one run each
# (a tenth of the 16 bytes a point the GPU state needs, as in BENCHMARKS.md "1 B points").
set -u
base=$(cd "$BASE" && pwd); new=$(cd "$NEW" && pwd)
rounds=${ROUNDS:-3}; out=${OUT:-/tmp}/gpu_paged.txt
w=${WORK:-/tmp/gpaged}; mkdir -p "$w"; cd "$w"
row() { # row <bin dir> <name> <input> <args...>: one timed build into s_<name>, a line of figures
  local bin=$1 name=$2 f=$3; shift 3
  rm -rf "s_$name"
  local t0 t1 j
  t0=$(date +%s.%N)
  j=$(/usr/bin/time -f '%M' -o rss.txt "$bin/mortar" build "$f" -o "s_$name" -q --json --engine gpu "$@" 2>err.txt | tr -d '\n')
  t1=$(date +%s.%N)
  if [ -z "$j" ]; then echo "R $f $name FAILED $(head -c 300 err.txt)"; return; fi
  echo "R $f $name $(python3 -c "
import json,sys
j=json.loads(sys.argv[1]); s=dict(j.get('gpu_steps',[]))
print(round($t1-$t0,3), j['seconds'], j['tree_seconds'], j['write_seconds'], int(open('rss.txt').read().split()[-1])*1024,
      'voxels', round(s.get('voxels',0),2), 'walks', int(s.get('voxel walks',0)), 'up_GB', round(s.get('upload bytes',0)/1e9,1),
      'expand', round(s.get('expand',0),2), 'number', round(s.get('number',0),2))" "$j")"
}
same() { # same <a> <b>: each store file byte for byte (a file neither store has is skipped)
  local line="S $1 $2"
  for x in nodes.bin hierarchy.bin source.las arrival.bin; do
    if [ ! -e "$1/$x" ] && [ ! -e "$2/$x" ]; then continue; fi
    if cmp -s "$1/$x" "$2/$x"; then line="$line $x:same"; else line="$line $x:DIFFERENT"; fi
  done
  echo "$line"
}
{
echo "machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(free -g | awk '/Mem:/{print $2}') GiB; $(nvidia-smi -L 2>/dev/null | head -1)"
"$new/mortar-gen" --points 100000000 --seed 1 -o g100.las >/dev/null
cat g100.las >/dev/null
for r in $(seq 1 "$rounds"); do
  row "$base" base g100.las --gpu-memory 160M
  row "$new" new g100.las --gpu-memory 160M
done
same s_base s_new
rm -rf s_base s_new g100.las
if [ "${BIG:-0}" = 1 ]; then
  t0=$(date +%s.%N); "$new/mortar-gen" --points 1000000000 --seed 1 -o big.las >/dev/null; t1=$(date +%s.%N)
  echo "generated $(stat -c %s big.las) bytes in $(python3 -c "print(round($t1-$t0,1))") s"
  cat big.las > /dev/null
  row "$new" new big.las --gpu-memory 1600M --memory 110G
  row "$base" base big.las --gpu-memory 1600M --memory 110G
  same s_base s_new
  rm -rf s_base s_new big.las
fi
} 2>&1 | tee "$out"
