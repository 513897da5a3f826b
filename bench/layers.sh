#!/usr/bin/env bash
# Layer-skipping LAZ decode (issue 13): `mortar batch --attributes all` against `--attributes
# none` (which decodes positions, RGB and intensity only) on LAS 1.4 layered LAZ, PDRF 7 and 8,
# made from the seeded synthetic set by laspy, with the bare decode (mortar-bench-decode) and
# laspy's own selective decode as references, in the same run.
# Usage: bench/layers.sh BIN_DIR PYTHON [POINTS] [RUNS]   (PYTHON has laspy and lazrs)
set -euo pipefail
bin=$(cd "$1" && pwd); py=$2; n=${3:-20000000}; runs=${4:-5}
dir=${BENCH_DIR:-/tmp/mortar-layers}; mkdir -p "$dir"; cd "$dir"
[ -f g.las ] || "$bin/mortar-gen" --points "$n" --seed 1 -o g.las
"$py" - <<'PY'
import laspy, os, time
las = None
for fmt in (7, 8):
    f = f"g-pdrf{fmt}.laz"
    if not os.path.exists(f):
        las = las or laspy.read("g.las")
        out = laspy.convert(las, point_format_id=fmt, file_version="1.4")
        if fmt == 8:
            out.nir = (out.intensity * 3).astype("u2")
        out.write(f, laz_backend=laspy.LazBackend.LazrsParallel)
    D = laspy.DecompressionSelection
    for name, sel in [("all", D.all()), ("xyz+rgb+intensity", D.base() | D.RGB | D.INTENSITY)]:
        ts = []
        for _ in range(3):
            t = time.time(); laspy.read(f, decompression_selection=sel, laz_backend=laspy.LazBackend.LazrsParallel); ts.append(time.time() - t)
        print(f"laspy {f} {name}: median {sorted(ts)[1]:.2f} s")
PY
hyperfine -w 1 -r "$runs" -N --export-json layers.json \
  "$bin/mortar-bench-decode g-pdrf7.laz" "$bin/mortar batch g-pdrf7.laz -o out.mbat --attributes all" "$bin/mortar batch g-pdrf7.laz -o out.mbat --attributes none" \
  "$bin/mortar-bench-decode g-pdrf8.laz" "$bin/mortar batch g-pdrf8.laz -o out.mbat --attributes all" "$bin/mortar batch g-pdrf8.laz -o out.mbat --attributes none" >/dev/null
"$py" -c "
import json
for r in json.load(open('layers.json'))['results']:
    print('%.3f s median  %s' % (r['median'], r['command']))"
