#!/usr/bin/env bash
# Load a Potree 2.0 octree directory (metadata.json, hierarchy.bin, octree.bin) in headless
# Chromium with potree-core + three.js, render it top-down, and write a JSON report.
#
#   tests/web/potree_check.sh DIR OUT_JSON [SHOT_PNG]
#
# Exit 0 when every node loaded without error, 1 otherwise (report.error says why), 2 on usage.
# Needs: node, tests/web/node_modules + dist (tests/web/install.sh), Debian chromium (installed
# here with apt-get when missing). Works offline after install.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
if [ $# -lt 2 ] || [ $# -gt 3 ]; then
  echo "usage: $0 DIR OUT_JSON [SHOT_PNG]" >&2
  exit 2
fi
dir="$1"; out="$2"; shot="${3:-}"

if [ -z "${CHROMIUM_BIN:-}" ] && ! command -v chromium >/dev/null 2>&1; then
  echo "potree_check: installing Debian chromium" >&2
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium) >&2
fi
if [ ! -d "$here/node_modules/puppeteer-core" ] || [ ! -f "$here/dist/main.js" ]; then
  bash "$here/install.sh" >&2
fi

child=""
cleanup() {
  # The HTTP server runs inside the node driver; ending it ends the server and the browser.
  if [ -n "$child" ] && kill -0 "$child" 2>/dev/null; then
    kill -TERM "$child" 2>/dev/null || true
    sleep 1
    kill -KILL "$child" 2>/dev/null || true
  fi
}
trap cleanup EXIT
trap 'exit 130' INT TERM

set +e
timeout -k 5 "${POTREE_CHECK_WALL_S:-75}" node --no-deprecation "$here/check.mjs" "$dir" "$out" ${shot:+"$shot"} &
child=$!
wait "$child"
rc=$?
child=""
set -e
if [ "$rc" -ne 0 ] && [ "$rc" -ne 1 ]; then
  # Killed or crashed before writing a report: write one.
  printf '{"loaded": false, "points": 0, "nodes": 0, "node_points_sum": 0, "covered_pixels": 0, "width": 800, "height": 600, "error": "driver exited with status %d"}\n' "$rc" > "$out"
  rc=1
fi
exit "$rc"
