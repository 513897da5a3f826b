#!/usr/bin/env bash
# Thread scaling of mortar batch on a many-core machine (run on the device).
set -u
cd "$(dirname "$0")"
D=/tmp/b; mkdir -p $D
echo "cores: $(nproc)"; grep -m1 "model name" /proc/cpuinfo; free -g | head -2
./mortar-gen --points 20000000 --seed 1 -o $D/s20m.las
./mortar-gen --points 20000000 --seed 1 -o $D/s20m.laz
for t in 1 2 4 8 16; do
  runs=3; [ $t -le 2 ] && runs=2
  for r in $(seq $runs); do
    s=$(date +%s%N); RAYON_NUM_THREADS=$t ./mortar-bench-decode $D/s20m.laz >/dev/null; e=$(date +%s%N)
    echo "laz-decode t=$t run=$r ms=$(( (e - s) / 1000000 ))"
    rm -f $D/o.mbat; echo "laz-batch t=$t run=$r $(RAYON_NUM_THREADS=$t ./mortar batch $D/s20m.laz -o $D/o.mbat --json | tr -d '\n ')"
    s=$(date +%s%N); RAYON_NUM_THREADS=$t ./mortar-bench-decode $D/s20m.las >/dev/null; e=$(date +%s%N)
    echo "las-read t=$t run=$r ms=$(( (e - s) / 1000000 ))"
    rm -f $D/o.mbat; echo "las-batch t=$t run=$r $(RAYON_NUM_THREADS=$t ./mortar batch $D/s20m.las -o $D/o.mbat --json | tr -d '\n ')"
  done
done
./mortar-gen --points 100000000 --seed 1 -o $D/s100m.las
for r in 1 2 3; do rm -f $D/o.mbat; echo "las100-batch t=16 run=$r $(./mortar batch $D/s100m.las -o $D/o.mbat --json | tr -d '\n ')"; done
