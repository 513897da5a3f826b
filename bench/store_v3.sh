#!/usr/bin/env bash
# Issue 28 (store v3): sizes and same-run build times.
#   bench/store_v3.sh BEFORE_DIR AFTER_DIR [POINTS] [REPS]
# BEFORE_DIR holds a version 2 `mortar` (e.g. a build of 5e09b4e), AFTER_DIR this version's
# `mortar`, `mortar-gen` and `mortar-bench-decode`. POTREE (default
# ../shared/tools/potree-converter/run) is PotreeConverter 2.1.2; DATA (default ../shared/data)
# the real scans. Default settings everywhere (no --memory). B and A (default v2 and v3) name
# the two binaries in the tables (e.g. B=codec1 A=codec2 for two version 3 binaries).
#
# 1. Sizes: for each input (two synthetic generators at POINTS points, LAS and LAZ, and real
#    scans), the input, the version 2 and version 3 stores' nodes.bin, the COPC and Potree
#    exports, PotreeConverter's output (-m random), and the ratios v3/COPC, v2/v3.
# 2. Builds of the synthetic LAS and LAZ, interleaved REPS times: version 2, version 3,
#    PotreeConverter -m random and poisson; the bare parallel decode; the disk's fdatasync
#    bandwidth (dd conv=fdatasync of 512 MiB) and the write floor: decode + bytes / bandwidth.
set -euo pipefail
before=$1
after=$2
points=${3:-20000000}
reps=${4:-3}
here=$(cd "$(dirname "$0")/.." && pwd)
potree=${POTREE:-$here/../shared/tools/potree-converter/run}
data=${DATA:-$here/../shared/data}
work=${WORK:-/tmp/mortar-store-v3}
mkdir -p "$work"
cd "$work"
[ -f g.las ] || "$after/mortar-gen" --points "$points" --seed 1 -o g.las >/dev/null
[ -f g.laz ] || "$after/mortar-gen" --points "$points" --seed 1 -o g.laz >/dev/null
[ -f cube.las ] || "$after/mortar-gen" --points "$points" --seed 2 --shape cube -o cube.las >/dev/null
inputs=(g.las cube.las)
for f in PDAL/test/data/las/autzen_trim.las lidR/inst/extdata/Megaplot@39ac7951.laz \
  lasR/inst/extdata/bcts/bcts_2.laz lasR/inst/extdata/bcts/bcts_3.laz; do
  [ -f "$data/$f" ] && inputs+=("$data/$f")
done
bytes() { du -sb "$1" | cut -f1; }
B=${B:-v2}; A=${A:-v3}
echo "| input | points | input bytes | $B store | $A store | $B/$A | COPC | $A/COPC | Potree export | PotreeConverter | $A/PotreeConverter |"
echo "|---|---|---|---|---|---|---|---|---|---|---|"
for f in "${inputs[@]}"; do
  rm -rf s2 s3 pc px c.copc.laz
  "$before/mortar" build "$f" -o s2 -q >/dev/null
  j=$("$after/mortar" build "$f" -o s3 -q --json)
  n=$(printf '%s' "$j" | python3 -c 'import json,sys; print(json.load(sys.stdin)["points"])')
  "$after/mortar" export s3 -o c.copc.laz -q >/dev/null
  "$after/mortar" export s3 -o px --format potree -q >/dev/null
  pcb=-
  if "$potree" "$f" -o pc -m random >/dev/null 2>&1; then pcb=$(bytes pc); fi
  b2=$(cat s2/nodes*.bin | wc -c); b3=$(cat s3/nodes*.bin | wc -c); bc=$(bytes c.copc.laz)
  python3 -c "
import sys
f,n,bi,b2,b3,bc,bp,pc=sys.argv[1:]
r=lambda a,b: '-' if b=='-' else f'{int(a)/int(b):.2f}'
print(f'| {f.split(\"/\")[-1]} | {n} | {bi} | {b2} | {b3} | {r(b2,b3)} | {bc} | {r(b3,bc)} | {bp} | {pc} | {r(b3,pc)} |')
" "$f" "$n" "$(bytes "$f")" "$b2" "$b3" "$bc" "$(bytes px)" "$pcb"
done
rm -rf s2 s3 pc px c.copc.laz

# 2. Build times.
dd if=/dev/zero of=dd.bin bs=8M count=64 conv=fdatasync 2> dd.txt
rm -f dd.bin
bw=$(python3 -c "
import re; t=open('dd.txt').read(); m=re.search(r'(\d+) bytes.*?, ([0-9.]+) s', t); print(int(m.group(1))/float(m.group(2)))")
results=results.txt
: > "$results"
for r in $(seq 1 "$reps"); do
  for ext in las laz; do
    for which in before after; do
      bin=${!which}/mortar
      rm -rf store
      j=$("$bin" build "g.$ext" -o store -q --json)
      printf '%s' "$j" | python3 -c "import json,sys; j=json.load(sys.stdin); print('$ext $which', j['seconds'], j['nodes_bytes'], j['engine'])" | tee -a "$results"
      rm -rf store
    done
    for m in random poisson; do
      rm -rf pc
      t0=$(date +%s.%N); "$potree" "g.$ext" -o pc -m $m >/dev/null 2>&1 || true; t1=$(date +%s.%N)
      echo "$ext potree-$m $(python3 -c "print($t1 - $t0)") $(bytes pc) -" | tee -a "$results"
    done
    j=$("$after/mortar-bench-decode" "g.$ext")
    printf '%s' "$j" | python3 -c "import json,sys; print('$ext decode', json.load(sys.stdin)['seconds'], 0, '-')" | tee -a "$results"
  done
done
rm -rf store pc
python3 - "$results" "$bw" "$B" "$A" <<'PY'
import sys, statistics as st
B, A = sys.argv[3], sys.argv[4]
rows = {}
for line in open(sys.argv[1]):
    ext, which, s, b, _ = line.split()
    rows.setdefault((ext, which), []).append((float(s), int(b)))
bw = float(sys.argv[2])
print(f"\nfdatasync bandwidth (dd, 512 MiB): {bw / 1e6:.0f} MB/s\n")
print(f"| input | {B} s | {A} s | {B}/{A} | PotreeConverter random s | poisson s | random/{A} | poisson/{A} | decode s | {A} bytes | floor s (decode + bytes/bw) | {A}/floor |")
print("|---|---|---|---|---|---|---|---|---|---|---|---|")
for ext in ("las", "laz"):
    m = lambda w: st.median(x[0] for x in rows[(ext, w)])
    b3 = st.median(x[1] for x in rows[(ext, "after")])
    v2, v3, pr, pp, dec = m("before"), m("after"), m("potree-random"), m("potree-poisson"), m("decode")
    floor = dec + b3 / bw
    print(f"| g.{ext} | {v2:.2f} | {v3:.2f} | {v2 / v3:.2f} | {pr:.2f} | {pp:.2f} | {pr / v3:.2f} | {pp / v3:.2f} | {dec:.2f} | {b3} | {floor:.2f} | {v3 / floor:.2f} |")
PY
