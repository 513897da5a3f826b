#!/usr/bin/env bash
# Issue 28 item 4: how soon readers of a partitioned build (input larger than --memory) see the
# cloud, and what the provisional commits cost. For each round: the build with the default
# --commit-every (5 s; EVERY=S sets it) watched by a poller that notes when each commit
# (hierarchy.bin's commit number) appears, and the same build with no commit before the end
# (--commit-every 1e9).
#   [EVERY=S] bench/live.sh MORTAR_BIN_DIR INPUT MEMORY [ROUNDS] [EXTRA BUILD ARGS...]
set -euo pipefail
bin=$(cd "$1" && pwd); in=$(realpath "$2"); mem=$3; rounds=${4:-3}; shift 4 || shift $#
work=${WORK:-/tmp/mortar-live}; rm -rf "$work"; mkdir -p "$work"; cd "$work"
echo "machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(free -g | awk '/Mem:/{print $2}') GiB"
echo "input: $in ($(stat -c %s "$in") B), --memory $mem, --commit-every ${EVERY:-5} $*"
for r in $(seq 1 "$rounds"); do
  rm -rf live quiet
  python3 - "$bin/mortar" "$in" "$mem" "$@" <<'PY'
import os, struct, subprocess, sys, time
exe, inp, mem, extra = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4:]
t0 = time.time()
every = os.environ.get("EVERY", "5")
p = subprocess.Popen([exe, "build", inp, "-o", "live", "--memory", mem, "--quiet", "--json",
                      "--commit-every", every] + extra,
                     stdout=subprocess.PIPE)
seen = {}
while p.poll() is None:
    try:
        h = open("live/hierarchy.bin", "rb").read(104)
        c, n, _, pts = struct.unpack_from("<QQQQ", h, 16)
        seen.setdefault(c, (time.time() - t0, n, pts))
    except (OSError, struct.error):
        pass
    time.sleep(0.002)
total = time.time() - t0
out = p.stdout.read().decode()
import json
j = json.loads(out)
last = j["commits"]
before = {c: v for c, v in seen.items() if c < last}
first = min(before.values())[0] if before else float("nan")
print(f"live: {total:6.2f} s, engine {j['engine']}, commits {last}, seen before the end {len(before)}, "
      f"first at {first:5.2f} s ({100*first/total:4.1f} % of the build), "
      f"points committed before the end: {sorted(v[2] for v in before.values())[-1:] if before else []}")
PY
  t0=$(date +%s.%N)
  "$bin/mortar" build "$in" -o quiet --memory "$mem" --commit-every 1e9 --quiet "$@"
  t1=$(date +%s.%N)
  echo "no commit before the end: $(python3 -c "print(round($t1 - $t0, 2))") s"
  if cmp -s live/nodes.bin quiet/nodes.bin && [ "$(ls live)" = "$(ls quiet)" ]; then
    echo "same nodes.bin and files"
  else
    echo "DIFFERENT stores"
  fi
done
