#!/usr/bin/env bash
# Issue 17's measurements of the GPU draw pass on the device (H200): where the time goes.
# Runs from the repository root with release binaries in $BIN (default .carry) and the four bcts
# strips in $DATA (default .carry); writes JSON lines and logs under $OUT (default bench-data/issue17).
# Method (device METHOD.md): warm-up, interleaved rounds, medians, SM/memory clocks logged
# every 200 ms next to the timings (clocks.csv; match by unix_ms), the same configuration timed
# in several rounds so that the noise is known.
set -uo pipefail
BIN=${BIN:-.carry}
DATA=${DATA:-.carry}
OUT=${OUT:-bench-data/issue17}
mkdir -p "$OUT"
nvidia-smi --query-gpu=name,driver_version,clocks.max.sm,clocks.max.mem,power.limit --format=csv > "$OUT/gpu.csv" 2>&1
nvidia-smi --query-gpu=timestamp,clocks.sm,clocks.mem,power.draw,temperature.gpu,utilization.gpu --format=csv -lms 200 > "$OUT/clocks.csv" 2>&1 &
SMI=$!
M=/tmp/bcts.mbat
[ -f $M ] || "$BIN/mortar" batch "$DATA"/bcts_*.laz -o $M --attributes none 2>&1 | tail -1
# The copy bandwidth, the ceiling of the ratios (device-to-device, bytes read + written).
python3 - <<'PY' 2>&1 | tee "$OUT/copy.txt"
import torch
n = 2 << 30
a = torch.empty(n, dtype=torch.uint8, device='cuda'); b = torch.empty_like(a)
a.random_(0, 255)
for _ in range(3): b.copy_(a)
torch.cuda.synchronize()
ts = []
for _ in range(20):
    s = torch.cuda.Event(enable_timing=True); e = torch.cuda.Event(enable_timing=True)
    s.record(); b.copy_(a); e.record(); e.synchronize(); ts.append(s.elapsed_time(e))
ts.sort(); m = ts[len(ts)//2]
print(f"copy {n/2**30:.0f} GiB: median {m:.3f} ms, {2*n/m/1e6:.0f} GB/s (read + write)")
PY
run() { local name=$1; shift; echo "== $name: $*" | tee -a "$OUT/bench.txt"; timeout 300 "$BIN/mortar-bench-gpu" $M "$@" > "$OUT/$name.jsonl" 2>> "$OUT/bench.txt"; echo "exit $?" >> "$OUT/bench.txt"; }
PHASE=${PHASE:-final}
if [ "$PHASE" = diagnose ]; then
# Run 1 (before the plan pass): where the draw pass's time goes.
# A: the kernels and the record order at every size, warm, two interleaved rounds.
run kernels --millions 500,1000,2000,3000 --frames 10 --variants ten --kernels 0,1,2,3 --orders scene,strided:97 --rounds 2 --warmup-ms 2000
# B: the issue's comparison as it was measured (no warm-up), three rounds: cold versus warm.
run variants --millions 1000,3000 --frames 15 --variants adaptive,ten,brute --rounds 3
# C: workgroup size.
run workgroups --millions 1000,3000 --frames 10 --variants ten --workgroups 64,128,256 --rounds 2 --warmup-ms 2000
elif [ "$PHASE" = final ]; then
# Run 3 (the plan pass, the growth fix): timings without any CPU work between them (the CPU
# comparisons of run 2 let the clocks fall), each configuration drawn for 0.5 s first.
run final --millions 500,1000,2000,3000 --frames 15 --variants adaptive,brute,ten --plans gpu,host --rounds 2 --config-warmup-ms 500
run closeup --millions 1000,3000 --frames 15 --view closeup --variants adaptive,brute --plans gpu,host --rounds 2 --config-warmup-ms 500
run atomics32 --millions 500,1000 --frames 10 --atomics 32 --variants adaptive,brute --plans gpu,host --config-warmup-ms 500
# Correctness at every size, apart from the timings: the GPU's keys against the CPU's.
run compare --millions 500,1000,2000,3000 --frames 1 --variants adaptive,brute --compare-cpu
run compare_closeup --millions 3000 --frames 1 --view closeup --variants adaptive,brute --compare-cpu
elif [ "$PHASE" = progressive ]; then
# Run 4: progressive loading against the measured host-to-device bandwidth, the new insert
# (slots computed by the scatter pass, records staged in parallel) against the old one
# ($BIN/mortar-bench-progressive-old, built from c581ab0) on the same machine, interleaved; and
# the WGSL hole filling + EDL against the CPU's, with their pass times.
python3 - <<'PY' 2>&1 | tee "$OUT/h2d.txt"
import torch, time
n = 1 << 30
dev = torch.empty(n, dtype=torch.uint8, device='cuda')
for pinned in (True, False):
    host = torch.empty(n, dtype=torch.uint8, pin_memory=pinned); host.fill_(7)
    for _ in range(2): dev.copy_(host); torch.cuda.synchronize()
    ts = []
    for _ in range(10):
        t = time.perf_counter(); dev.copy_(host); torch.cuda.synchronize(); ts.append(time.perf_counter() - t)
    ts.sort(); m = ts[len(ts)//2]
    print(f"host-to-device {n/2**30:.0f} GiB, {'pinned' if pinned else 'pageable'}: median {m*1e3:.1f} ms, {n/m/1e9:.1f} GB/s")
PY
nproc | sed 's/^/host cores: /' | tee -a "$OUT/h2d.txt"
prog() { local name=$1 bin=$2; shift 2; echo "== $name: $bin $*" | tee -a "$OUT/bench.txt"; timeout 240 "$BIN/$bin" "$@" > "$OUT/$name.jsonl" 2>> "$OUT/bench.txt"; echo "exit $?" >> "$OUT/bench.txt"; }
for round in $(seq ${ROUNDS:-2}); do
prog new-$round mortar-bench-progressive --points 1e9 --piece 16000000
prog old-$round mortar-bench-progressive-old --points 1e9 --piece 16000000
done
# From memory (every point generated first): loading alone, then with frames while loading,
# each piece prepared on another thread while the render thread uploads and draws.
prog pre-noframes mortar-bench-progressive --points 1e9 --piece 16000000 --pregenerate --no-load-frames --max-frames 5
prog pre-thread-16m mortar-bench-progressive --points 1e9 --piece 16000000 --pregenerate --prepare-thread --max-frames 5
prog pre-thread-4m mortar-bench-progressive --points 1e9 --piece 4000000 --pregenerate --prepare-thread --max-frames 5
prog pre-thread-2m mortar-bench-progressive --points 1e9 --piece 2000000 --pregenerate --prepare-thread --max-frames 5
prog pre-2e9 mortar-bench-progressive --points 2e9 --piece 16000000 --pregenerate --no-load-frames --max-frames 5
# Hole filling and EDL: the GPU PNG against the CPU PNG, and the pass times (5 runs each size).
[ "${POST:-1}" = 1 ] && for size in "1920 1080" "3840 2160"; do
set -- $size
for k in 1 2 3 4 5; do
"$BIN/mortar" render "$DATA"/bcts_*.laz --backend gpu --hole-fill --edl --width $1 --height $2 --json -o /tmp/post-gpu.png >> "$OUT/post-$1.jsonl" 2>> "$OUT/bench.txt"
done
"$BIN/mortar" render "$DATA"/bcts_*.laz --backend cpu --hole-fill --edl --width $1 --height $2 --json -o /tmp/post-cpu.png >> "$OUT/post-$1-cpu.jsonl" 2>> "$OUT/bench.txt"
cmp /tmp/post-gpu.png /tmp/post-cpu.png && echo "post $1x$2: GPU PNG == CPU PNG" | tee -a "$OUT/bench.txt" || echo "post $1x$2: PNGs DIFFER" | tee -a "$OUT/bench.txt"
done
else
# Run 2: the plan pass against host planning, kernel 0 against the prefetch kernel 4, every
# variant, with the GPU's keys compared to the CPU's after every measurement.
run final --millions 500,1000,2000,3000 --frames 10 --variants adaptive,brute,ten --kernels 0,4 --plans gpu,host --rounds 2 --warmup-ms 3000 --compare-cpu
# What the exact division costs (plain WGSL division: keys may differ from the CPU's).
run division --millions 1000,3000 --frames 10 --variants adaptive --kernels 0,4 --divisions default,plain --rounds 2 --warmup-ms 2000
fi
kill $SMI
grep -v '^{' "$OUT/bench.txt" | grep -v "^adapter\|tiles of" | tail -120
