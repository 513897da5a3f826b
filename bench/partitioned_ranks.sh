#!/usr/bin/env bash
# What keeping arrival ranks costs the partitioned engine (arrival.bin written from
# .partition/ranks.bin): the build of POINTS points of mortar-gen (seed 1) under --memory MEM,
# by the binary BASE (without ranks) and NEW (with), interleaved ROUNDS times, wall time and
# peak RSS (`/usr/bin/time`); then checks that NEW's arrival.bin is the sorted engine's.
# Usage: BASE=old/dir NEW=target/release OUT=/tmp/x POINTS=30000000 MEM=1G ROUNDS=3 bash bench/partitioned_ranks.sh
set -euo pipefail
BASE=$(realpath "$BASE/mortar"); NEWB=$(realpath "${NEW:-target/release}/mortar")
G=$(realpath "${NEW:-target/release}/mortar-gen")
HERE=$(cd "$(dirname "$0")" && pwd); OUT=${OUT:-/tmp/partitioned-ranks}; POINTS=${POINTS:-30000000}; MEM=${MEM:-1G}; ROUNDS=${ROUNDS:-3}
mkdir -p "$OUT"; cd "$OUT"
[ -f big.las ] || "$G" --points "$POINTS" --seed 1 -o big.las > /dev/null
echo "input: $POINTS points, --memory $MEM, $(nproc) threads"
for r in $(seq 1 "$ROUNDS"); do
  for b in base new; do
    bin=$BASE; [ $b = new ] && bin=$NEWB
    rm -rf s-$b; sync
    /usr/bin/time -f "%e %M" -o time.txt "$bin" build big.las -o s-$b -q --memory "$MEM" --json > j-$b.json
    read -r wall rss < time.txt
    eng=$(grep -o '"engine": "[a-z]*"' j-$b.json)
    echo "round $r $b: $wall s, peak RSS $rss kB, $eng, arrival.bin $(stat -c %s s-$b/arrival.bin 2>/dev/null || echo none) bytes"
  done
done
cmp s-base/source.las s-new/source.las; python3 "$HERE/same_tree.py" s-base s-new
rm -rf sorted; "$NEWB" build big.las -o sorted -q --engine sorted
cmp sorted/arrival.bin s-new/arrival.bin && echo "arrival.bin of the partitioned engine = the sorted engine's"
