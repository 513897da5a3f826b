#!/usr/bin/env bash
# Issue 30 §2: a COPC file over HTTP against the same file read locally, same run. Serves the
# 20 M-point COPC export of bench/lod_sources.sh with npm http-server (tests/web/install.sh) on
# 127.0.0.1 and renders the framed view and the closeup (1920x1080, CPU rasterizer, defaults)
# from the URL and from the file, REPS times each, interleaved: median seconds, bytes fetched.
#   bash bench/http.sh [BIN_DIR] [REPS]
set -euo pipefail
B=${1:-target/release}; REPS=${2:-3}
D=${TMPDIR:-/tmp}/mortar-lod-sources; mkdir -p "$D"
[ -f "$D/g20.las" ] || "$B/mortar-gen" --points 20000000 --seed 1 -o "$D/g20.las" >/dev/null 2>&1
[ -f "$D/g20.copc.laz" ] || "$B/mortar" export "$D/g20.las" -o "$D/g20.copc.laz" -q
SRV=tests/web/node_modules/.bin/http-server
[ -x "$SRV" ] || { echo "no $SRV: bash tests/web/install.sh"; exit 1; }
PORT=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')
"$SRV" "$D" -p "$PORT" -a 127.0.0.1 -s -c-1 & SPID=$!
trap 'kill $SPID 2>/dev/null' EXIT
sleep 1
URL=http://127.0.0.1:$PORT/g20.copc.laz
run() { # run NAME ARGS...
  local name=$1; shift
  for r in $(seq "$REPS"); do
    for src in "$URL" "$D/g20.copc.laz"; do
      local t0=$(date +%s.%N)
      "$B/mortar" render "$src" -o "$D/h.png" --width 1920 --height 1080 --backend cpu --json "$@" > "$D/h.json" 2>/dev/null
      local t=$(echo "$(date +%s.%N) - $t0" | bc)
      python3 -c "import json,sys; j=json.load(open('$D/h.json'))['lod_source']; print('$src'.startswith('http'), $t, j['bytes_fetched'], j['bytes_read'], j['bytes'])"
    done
  done | python3 -c "
import sys, statistics
rows = [l.split() for l in sys.stdin]
for remote in ('True', 'False'):
    r = [x for x in rows if x[0] == remote]
    t = sorted(float(x[1]) for x in r)
    f, rd, b = int(r[0][2]), int(r[0][3]), int(r[0][4])
    kind = 'http ' if remote == 'True' else 'local'
    print(f'$name {kind}: median {statistics.median(t):.2f} s {[round(x, 2) for x in t]}, fetched {f / 1e6:.1f} MB ({100 * f / b:.1f} %), read {rd / 1e6:.1f} of {b / 1e6:.1f} MB')
"
}
echo "machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs); server: npm http-server on 127.0.0.1"
run "copc 20M closeup" --target 500100,5000100,0 --eye 500100,5000040,60
run "copc 20M framed"
