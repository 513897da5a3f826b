#!/usr/bin/env bash
# The coder A/B on the device (BENCHMARKS.md, "The coder gathers its points"): binaries in
# .carry/<version>/ (VERSIONS, the first is the reference; head holds mortar-gen), 20 M and 100 M
# points of mortar-gen, stores compared with the first version's, 4 interleaved rounds of both
# engines and PotreeConverter at 100 M; LAZ=1 adds bench/gpu_engine_scale.sh laz with .carry/next.
#   VERSIONS="head coder" OUT=/tmp bash bench/coder_ab_device.sh
set -u
tar xzf .carry/bins.tgz -C .carry
for f in .gl/*.deb; do dpkg -x $f /; done; ldconfig
[ -f /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json ] && export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
nvidia-smi -L; grep -m1 "model name" /proc/cpuinfo; nproc
V=${VERSIONS:-head coder}
W=/tmp/cab; mkdir -p $W; R=$(pwd)
cd $W
for n in 20 100; do $R/.carry/head/mortar-gen --points ${n}000000 --seed 1 -o g$n.las > /dev/null; done
# equality: every version's store equals head's, both engines
for f in g20.las g100.las; do for e in sorted gpu; do
  rm -rf ref; $R/.carry/head/mortar build $f -o ref -q --engine $e
  for v in $V; do [ $v = head ] && continue; rm -rf s; $R/.carry/$v/mortar build $f -o s -q --engine $e
    d=0; for x in nodes.bin hierarchy.bin source.las; do cmp -s ref/$x s/$x || d=1; done
    echo "EQ $f $e $v $([ $d = 0 ] && echo SAME || echo DIFFERENT)"; done
done; done
rm -rf ref s
for round in 1 2 3 4; do
 for f in g20.las g100.las; do
  for v in $V; do for e in sorted gpu; do
    rm -rf s
    j=$($R/.carry/$v/mortar build $f -o s -q --json --engine $e | tr -d '\n ')
    echo "R $f $v $e $(python3 -c "import json,sys; j=json.loads(sys.argv[1]); print(j['seconds'], j['read_seconds'], j['sort_seconds'], j['tree_seconds'], j['write_seconds'], j['peak_rss_bytes'])" "$j")"
  done; done
  if [ $f = g100.las ]; then rm -rf pc; t0=$(date +%s.%N); $R/.carry/potree/run $f -o pc -m random >/dev/null 2>&1; t1=$(date +%s.%N); echo "R $f potree random $(python3 -c "print($t1 - $t0)") 0 0 0 0 0"; rm -rf pc; fi
 done
done | tee $OUT/rows.txt
python3 - $OUT/rows.txt <<'PY'
import sys, statistics as st
rows={}
for l in open(sys.argv[1]):
    p=l.split()
    if p[0]=='R': rows.setdefault((p[1],p[2],p[3]),[]).append([float(x) for x in p[4:]])
for k in sorted(rows):
    v=rows[k]; med=[st.median(c) for c in zip(*v)]
    print(k, 'n=%d'%len(v), 'total %.3f read %.3f sort %.3f tree %.3f write %.3f rssGB %.2f'%(med[0],med[1],med[2],med[3],med[4],med[5]/1e9), 'all', [round(x[0],3) for x in v])
PY
cd $R
[ "${LAZ:-0}" = 1 ] && BIN=.carry/next OUT=$OUT WORK=/tmp/gs bash bench/gpu_engine_scale.sh laz 3 > /dev/null 2>&1; tail -12 $OUT/gpu_engine_scale.txt 2>/dev/null
