#!/usr/bin/env bash
# issue 15: 100 M synthetic points as 16 tiles (4 x 4 of 250 m), N = 1..16 (BIN: the binaries, default .carry/bin)
set -u
mkdir -p /tmp/t
for i in 0 1 2 3; do for j in 0 1 2 3; do
  ${BIN:-.carry/bin}/mortar-gen --points 6250000 --seed $((i * 4 + j + 1)) --extent 250 --origin $((500000 + 250 * i)),$((5000000 + 250 * j)),0 -o /tmp/t/t$i$j.las >/dev/null &
done; done; wait
du -sh /tmp/t
WORK=/tmp/dw bash bench/distributed.sh ${BIN:-.carry/bin} "/tmp/t" "1 2 4 8 16" 4G 2>&1 | tee ${OUT:-/tmp}/distributed100m-tiles.txt
