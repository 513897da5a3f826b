#!/usr/bin/env bash
# Hostile density and --memory (issue 26, item 2): peak RSS (the kernel's, /usr/bin/time -v),
# wall time and points back for `mortar build` and `mortar export` on inputs of mortar-gen's
# hostile shapes, beside copc_converter (`cargo install copc_converter`) in the same run.
#
#   bench/dense.sh OUT_DIR POINTS "MEMORY..." [RUNS] [SHAPES]
#   bench/dense.sh /tmp/dense 20000000 "1G 2G" 3 "coincident"
#
# Env: MORTAR (default target/release/mortar), MORTAR_BEFORE (an older binary, measured in the
# same run when set), MORTAR_GEN, COPCC (copc_converter), PY (a Python with laspy and lazrs,
# which counts the points of every COPC file). Prints one Markdown row per command: the median
# of RUNS runs (time, peak RSS) and the points laspy reads back.
set -euo pipefail
out=$1 points=$2 memories=$3 runs=${4:-3} shapes=${5:-"coincident cube duplicates extra192 onechunk"}
here="$(cd "$(dirname "$0")/.." && pwd)"
mortar=${MORTAR:-$here/target/release/mortar}
gen=${MORTAR_GEN:-$here/target/release/mortar-gen}
copcc=${COPCC:-$(command -v copc_converter || true)}
py=${PY:-$here/.ci-venv/bin/python}
mkdir -p "$out"

input() {  # the input file of a shape
  case $1 in
    coincident|cube|duplicates) f="$out/$1-$points.las"; [ -f "$f" ] || "$gen" --points "$points" --shape "$1" -o "$f" ;;
    extra192) f="$out/extra192-$points.las"; [ -f "$f" ] || "$gen" --points "$points" --extra-bytes 192 -o "$f" ;;
    onechunk) f="$out/onechunk-$points.laz"; [ -f "$f" ] || "$gen" --points "$points" --laz-chunk "$points" -o "$f" ;;
  esac
  echo "$f"
}

count() {  # points in a COPC file (laspy) or a store (mortar info)
  if [ -d "$1" ]; then "$mortar" info --json "$1" | grep -o '"point_count": *[0-9]*' | head -1 | grep -o '[0-9]*$'
  elif [ -f "$1" ]; then "$py" -c "import laspy,sys; print(len(laspy.read(sys.argv[1]).points))" "$1" 2>/dev/null || echo "laspy cannot read it"
  else echo "-"; fi
}

median() { sort -n | awk '{a[NR]=$1} END{print (NR%2 ? a[(NR+1)/2] : (a[NR/2]+a[NR/2+1])/2)}'; }

measure() {  # label result command...: RUNS runs; prints the row
  local label=$1 result=$2; shift 2
  local ts=() rs=() rc=0
  for _ in $(seq "$runs"); do
    rm -rf "$result"
    /usr/bin/time -v -o "$out/time.txt" "$@" >/dev/null 2>"$out/err.txt" || rc=$?
    ts+=("$(awk -F': ' '/Elapsed/{split($2,t,":"); print (length(t)==3 ? t[1]*3600+t[2]*60+t[3] : t[1]*60+t[2])}' "$out/time.txt")")
    rs+=("$(awk -F': ' '/Maximum resident/{print $2}' "$out/time.txt")")
  done
  local t r n
  t=$(printf '%s\n' "${ts[@]}" | median)
  r=$(printf '%s\n' "${rs[@]}" | median)
  if [ "$rc" -eq 0 ]; then n=$(count "$result"); else n="refused: $(head -c 120 "$out/err.txt" | tr '\n' ' ')"; fi
  printf '| %s | %.2f s | %d MB | %s |\n' "$label" "$t" "$((r / 1000))" "$n"
  rm -rf "$result"
}

echo "| command ($points points) | time (median of $runs) | peak RSS | points back |"
echo "|---|---|---|---|"
for shape in $shapes; do
  f=$(input "$shape")
  for mem in $memories; do
    for bin in ${MORTAR_BEFORE:+before} after; do
      b=$mortar; [ "$bin" = before ] && b=$MORTAR_BEFORE
      measure "$shape: mortar ($bin) export --memory $mem" "$out/m.copc.laz" "$b" export "$f" -o "$out/m.copc.laz" --memory "$mem"
      measure "$shape: mortar ($bin) build --memory $mem" "$out/store" "$b" build "$f" -o "$out/store" --memory "$mem"
    done
    if [ -n "$copcc" ]; then
      measure "$shape: copc_converter --memory-limit $mem" "$out/c.copc.laz" "$copcc" "$f" "$out/c.copc.laz" --memory-limit "$mem" --progress plain --temp-dir "$out"
    fi
  done
done
