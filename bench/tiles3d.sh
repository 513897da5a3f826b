#!/usr/bin/env bash
# Issue 30 §3: `mortar export --format 3dtiles` against py3dtiles (PyPI) on the same input in
# the same run, REPS times each, interleaved: median wall seconds (/usr/bin/time), peak RSS and
# output bytes. The input is the four lasR bcts tiles (2.83 M real airborne points, NAD83 / BC
# Albers) merged into one LAS file by `mortar sort` (py3dtiles hangs on LAZ input here).
# Like for like: both place the tiles on the globe (EPSG:4978), both write glTF tiles (3D Tiles
# 1.1), both carry intensity and classification. mortar runs with its defaults.
#   bash bench/tiles3d.sh [BIN_DIR] [REPS] [PY3DTILES]
set -euo pipefail
B=${1:-target/release}; REPS=${2:-3}; P3=${3:-py3dtiles}
DATA=${MORTAR_TEST_DATA:-../shared/data}
D=${TMPDIR:-/tmp}/mortar-tiles3d-bench; mkdir -p "$D"
IN=$D/bcts.las
[ -f "$IN" ] || "$B/mortar" sort "$DATA"/lasR/inst/extdata/bcts/bcts_*.laz -o "$IN" -q
for r in $(seq "$REPS"); do
  rm -rf "$D/m" "$D/p"
  /usr/bin/time -f "mortar %e %M" "$B/mortar" export "$IN" -o "$D/m" --format 3dtiles -q 2>> "$D/times-$$"
  echo "mortar_bytes $(du -sb "$D/m" | cut -f1)" >> "$D/times-$$"
  /usr/bin/time -f "py3dtiles %e %M" "$P3" convert "$IN" --out "$D/p" --overwrite --srs_out 4978 \
    --spec-version 1.1 --extra-fields intensity --extra-fields classification > /dev/null 2>> "$D/times-$$"
  echo "py3dtiles_bytes $(du -sb "$D/p" | cut -f1)" >> "$D/times-$$"
done
python3 - "$D/times-$$" <<'PY'
import sys, statistics, collections
t = collections.defaultdict(list); rss = collections.defaultdict(list); b = collections.defaultdict(list)
for line in open(sys.argv[1]):
    f = line.split()
    if len(f) == 3 and f[0] in ("mortar", "py3dtiles"):
        t[f[0]].append(float(f[1])); rss[f[0]].append(int(f[2]) / 1024)
    elif len(f) == 2 and f[0].endswith("_bytes"):
        b[f[0][:-6]].append(int(f[1]))
for k in ("mortar", "py3dtiles"):
    print(f"{k:10s} median {statistics.median(t[k]):7.2f} s {t[k]}  peak RSS {max(rss[k]):.0f} MiB  output {statistics.median(b[k]) / 1e6:.1f} MB")
print(f"speed-up {statistics.median(t['py3dtiles']) / statistics.median(t['mortar']):.1f}x; size ratio mortar/py3dtiles {statistics.median(b['mortar']) / statistics.median(b['py3dtiles']):.2f}")
PY
rm -f "$D/times-$$"
