#!/usr/bin/env bash
# One run each of the exports of a large input at the default --memory 2G (the partitioned
# path when the input needs more) against copc_converter and PotreeConverter: wall seconds,
# peak RSS, output bytes.
#   bench/export_big.sh MORTAR_BIN_DIR COPC_CONVERTER POTREE_RUN INPUT
set -u
bin=$(cd "$1" && pwd); copc=$2; potree=$3; in=$(realpath "$4")
work=${WORK:-/tmp/mortar-export-big}; mkdir -p "$work"; cd "$work"
t() { local l=$1 o=$2; shift 2; rm -rf "$o"; /usr/bin/time -f "%e %M" -o tt "$@" > /dev/null 2> err || echo "$l FAILED $(tail -3 err)"; echo "$l: $(cat tt) $(du -sb "$o" | cut -f1)"; rm -rf "$o"; }
echo "machine: $(nproc) cores, $(free -g | awk '/Mem:/{print $2}') GiB; input $in $(stat -c %s "$in") B"
t mortar-copc-2G out.copc.laz "$bin/mortar" export "$in" -o out.copc.laz --memory 2G
t copc_converter cc.copc.laz "$copc" "$in" cc.copc.laz --progress plain
t mortar-potree-2G pot "$bin/mortar" export "$in" -o pot --format potree --memory 2G
t potreeconverter pc "$potree" "$in" -o pc
