#!/usr/bin/env bash
# Issue 29 on the device: the GPU engine's --memory promise on a discrete GPU (32 bytes a point
# counted) on hostile density: every point at one position, every record eight times, and the
# airborne synthetic for contrast. For each input and budget: accepted or refused (the message
# names the need), and for an accepted build the OS's peak RSS against the budget.
#   BIN=.carry/bin bash bench/gpu_engine_hostile_device.sh [POINTS]
# Results go to ${OUT:-/tmp}/gpu_engine_hostile.txt.
set -u
bin=$(cd "${BIN:-.carry/bin}" && pwd); n=${1:-20000000}; out=${OUT:-/tmp}/gpu_engine_hostile.txt
w=${WORK:-/tmp/gpuh}; mkdir -p "$w"; cd "$w"
{
echo "machine: $(nproc) cores, $(free -g | awk '/Mem:/{print $2}') GiB; $(nvidia-smi -L 2>/dev/null | head -1)"
for shape in coincident duplicates airborne; do
  pts=$n; [ $shape = duplicates ] && pts=$(( n / 8 ))
  "$bin/mortar-gen" --points $pts --shape $shape --seed 1 -o $shape.las >/dev/null 2>&1
  for budget in ${BUDGETS:-1G 1500M 2G 4G}; do
    rm -rf s
    rm -f rss.txt; tm=(); [ -x /usr/bin/time ] && tm=(/usr/bin/time -f "%M" -o rss.txt)
    "${tm[@]}" "$bin/mortar" build $shape.las -o s --engine gpu --memory $budget --json > j.json 2> err.txt
    rc=$?
    if [ $rc = 0 ]; then
      python3 - "$shape" "$budget" "$(cat rss.txt 2>/dev/null || echo 0)" <<'PY'
import json, sys
shape, budget, rss_kb = sys.argv[1], sys.argv[2], int(sys.argv[3].split()[-1])
j = json.load(open("j.json"))
rss_kb = rss_kb or j["peak_rss_bytes"] // 1024
units = {"M": 1 << 20, "G": 1 << 30}
b = int(budget[:-1]) * units[budget[-1]]
print(f"H {shape} points {j['points']} budget {budget}: accepted, peak RSS {rss_kb * 1024 / 1e6:.0f} MB "
      f"(time -v) / {j['peak_rss_bytes'] / 1e6:.0f} MB (getrusage), {100 * rss_kb * 1024 / b:.0f} % of the budget, "
      f"{j['seconds']:.2f} s, {'WITHIN' if rss_kb * 1024 <= b else 'OVER'}")
PY
    else
      echo "H $shape budget $budget: exit $rc: $(tail -c 300 err.txt | tr '\n' ' ')"
    fi
  done
done
} 2>&1 | tee "$out"
