#!/usr/bin/env bash
# Issue 28 item 3 on the 16-core device: default-settings builds against PotreeConverter 2.1.2
# (-m random and poisson) on the same inputs in the same run, the bare parallel decode, and the
# disk's fdatasync bandwidth (write floor). Inputs are generated there (mortar-gen --seed 1).
#   BIN=.carry/bin POTREE=.carry/potree/run bash bench/store_v3_device.sh [REPS]
# BIN holds mortar, mortar-gen, mortar-bench-decode; results go to ${OUT:-/tmp}/store_v3_device.txt.
set -u
bin=$(cd "${BIN:-.carry/bin}" && pwd); potree=$(realpath "${POTREE:-.carry/potree/run}")
reps=${1:-3}; out=${OUT:-/tmp}/store_v3_device.txt
w=${WORK:-/tmp/sv3}; mkdir -p "$w"; cd "$w"
{
echo "machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(free -g | awk '/Mem:/{print $2}') GiB"
"$bin/mortar-gen" --points 20000000 --seed 1 -o g20.las >/dev/null
"$bin/mortar-gen" --points 20000000 --seed 1 -o g20.laz >/dev/null
"$bin/mortar-gen" --points 100000000 --seed 1 -o g100.las >/dev/null
ls -l g20.las g20.laz g100.las
dd if=/dev/zero of=dd.bin bs=8M count=128 conv=fdatasync 2>&1 | tail -1; rm -f dd.bin
for r in $(seq 1 "$reps"); do
  for f in g20.las g20.laz g100.las; do
    rm -rf s; j=$("$bin/mortar" build $f -o s -q --json | tr -d '\n ')
    echo "R $f mortar $(python3 -c "import json,sys; j=json.loads(sys.argv[1]); print(j['seconds'], j['nodes_bytes'], j['engine'])" "$j")"
    rm -rf s
    echo "R $f decode $("$bin/mortar-bench-decode" $f | python3 -c 'import json,sys; print(json.load(sys.stdin)["seconds"], 0, "-")')"
    for m in random poisson; do
      [ $m = poisson ] && [ $f = g100.las ] && [ $r -gt 2 ] && continue
      rm -rf pc; t0=$(date +%s.%N); "$potree" $f -o pc -m $m >/dev/null 2>&1; t1=$(date +%s.%N)
      echo "R $f potree-$m $(python3 -c "print($t1 - $t0)") $(du -sb pc | cut -f1) -"; rm -rf pc
    done
  done
done
} 2>&1 | tee "$out"
python3 - "$out" <<'PY'
import sys, re, statistics as st
rows = {}
bw = None
for line in open(sys.argv[1]):
    m = re.search(r'(\d+) bytes .*, ([0-9.]+) s', line)
    if m: bw = int(m.group(1)) / float(m.group(2))
    if line.startswith("R "):
        _, f, w, s, b, _e = line.split()
        rows.setdefault((f, w), []).append((float(s), int(b)))
print(f"\nfdatasync bandwidth: {bw/1e6:.0f} MB/s\n")
print("| input | mortar s | PotreeConverter random s | poisson s | random/mortar | poisson/mortar | decode s | decode/mortar | store bytes | floor s | mortar/floor |")
print("|---|---|---|---|---|---|---|---|---|---|---|")
for f in ("g20.las", "g20.laz", "g100.las"):
    m = lambda w: st.median(x[0] for x in rows[(f, w)])
    mo, pr, pp, dec = m("mortar"), m("potree-random"), m("potree-poisson"), m("decode")
    b = st.median(x[1] for x in rows[(f, "mortar")]); floor = dec + b / bw
    n = len(rows[(f, "mortar")])
    print(f"| {f} | {mo:.2f} | {pr:.2f} | {pp:.2f} | {pr/mo:.2f} | {pp/mo:.2f} | {dec:.2f} | {dec/mo:.2f} | {b} | {floor:.2f} | {mo/floor:.2f} |  (n={n})")
PY
