#!/usr/bin/env bash
set -u
cd "$(dirname "$0")"
D=/tmp/r; mkdir -p $D
echo "cores: $(nproc)"; grep -m1 "model name" /proc/cpuinfo
./mortar-gen --points 20000000 --seed 1 -o $D/s20m.las && ./mortar batch $D/s20m.las -o $D/s20m.mbat
for t in 16 8 4 2; do
  ./mortar-bench-render $D/s20m.mbat --views iso,closeup --runs 7 --threads $t --label s20m-t$t --out $OUT 2>&1 | grep -E "^- "
done
./mortar-gen --points 100000000 --seed 1 -o $D/s100m.las && ./mortar batch $D/s100m.las -o $D/s100m.mbat && rm $D/s100m.las
./mortar-bench-render $D/s100m.mbat --views iso,closeup --runs 5 --threads 16 --label s100m-t16 --out $OUT 2>&1 | grep -E "^- "
rm -f $OUT/*.png
