#!/usr/bin/env bash
# What keeping arrival ranks costs a distributed build (each part's arrival.bin, listed again
# by the merge): the input planned into N jobs, the jobs run at once with one thread each, then
# merged, by the binary BASE (no ranks in parts or store) and NEW (with), interleaved ROUNDS
# times; wall seconds of the jobs and of the merge, the merge's share of the build, the parts'
# and the store's arrival.bin bytes; then checks that NEW's store has the one-machine build's
# arrival.bin and is extended in place by `--append` of a small flight.
# Usage: BASE=old/dir NEW=target/release IN=x.las NS="4 16" MEM=1G ROUNDS=2 bash bench/distributed_ranks.sh
set -euo pipefail
BASEB=$(realpath "$BASE/mortar"); NEWB=$(realpath "${NEW:-target/release}/mortar")
G=$(realpath "${NEW:-target/release}/mortar-gen"); IN=$(realpath "$IN")
NS=${NS:-4 16}; MEM=${MEM:-1G}; ROUNDS=${ROUNDS:-2}; OUT=${OUT:-/tmp/distributed-ranks}
mkdir -p "$OUT"; cd "$OUT"
echo "input: $IN, $(nproc) threads, --memory $MEM per job"
now() { date +%s.%N; }
for n in $NS; do
  "$NEWB" plan "$IN" --jobs "$n" -o plan$n.json --quiet
  for r in $(seq 1 "$ROUNDS"); do
    for b in base new; do
      bin=$BASEB; [ $b = new ] && bin=$NEWB
      rm -rf parts-$b store-$b; mkdir parts-$b; sync
      t0=$(now)
      for ((i = 0; i < n; i++)); do
        "$bin" build --plan plan$n.json --job "$i" -o "parts-$b/p$(printf %03d "$i")" --threads 1 --memory "$MEM" --quiet &
      done
      wait
      t1=$(now); "$bin" merge parts-$b/p* -o store-$b --quiet; t2=$(now)
      pa=$( (cat parts-$b/p*/arrival.bin 2>/dev/null || true) | wc -c)
      sa=$(stat -c %s store-$b/arrival.bin 2>/dev/null || echo 0)
      awk -v n="$n" -v r="$r" -v b="$b" -v a="$t0" -v j="$t1" -v m="$t2" -v pa="$pa" -v sa="$sa" 'BEGIN {
        printf "N=%d round %d %s: jobs %.2f s, merge %.2f s (%.1f %% of jobs + merge), parts arrival.bin %d B, store arrival.bin %d B\n",
          n, r, b, j - a, m - j, 100 * (m - j) / (m - a), pa, sa }'
    done
  done
done
rm -rf one; "$NEWB" build "$IN" -o one --quiet
cmp one/arrival.bin store-new/arrival.bin && echo "store arrival.bin = the one-machine build's"
[ -f day.las ] || "$G" --points 100000 --seed 7 --extent 300 --origin 500300,5000300,0 -o day.las > /dev/null
"$NEWB" build --append store-new day.las --quiet --json | grep -E '"(kept_nodes|seconds)"'
