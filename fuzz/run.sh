#!/usr/bin/env bash
# Builds and runs mortar's fuzz targets (libFuzzer on the stable toolchain; FUZZING.md).
#
#   fuzz/run.sh SECONDS [JOBS]                 build every target, run each for SECONDS
#   fuzz/run.sh --bin-dir DIR SECONDS [JOBS]   run the built binaries in DIR (no cargo needed)
#   fuzz/run.sh --build [DIR]                  only build; with DIR, copy stripped binaries there
#   fuzz/run.sh --package DIR                  build and lay out DIR to run elsewhere: bin/ (stripped
#                                              binaries), corpus/, run.sh; then
#                                              `DIR/run.sh --bin-dir DIR/bin SECONDS JOBS` there
#
#   fuzz/run.sh --report OUT                   the table of an earlier run's logs in OUT
#
# Options (before SECONDS): --targets a,b,c   --out DIR (working corpora, crash files, logs;
# default fuzz/out or DIR/out)   --corpus DIR (seed corpora; default fuzz/corpus or DIR/corpus).
# JOBS > 1 runs libFuzzer's fork mode with JOBS workers per target (targets one after another).
# Each target runs with -timeout=10 (a hang is an input taking 10 s) and -rss_limit_mb=2048; a
# single allocation over 256 MiB aborts (the targets' allocator): all are crashes. Prints a
# Markdown table (executions, exec/s, coverage, crashes) and exits 1 when a target found a crash,
# hang or huge allocation; the inputs are in OUT/artifacts/<target>/ (printed as base64 too with
# FUZZ_PRINT_ARTIFACTS=1).
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
all_targets="las_header vlr_records las_input laz_pointwise batch_file store lod_index"

bin_dir="" mode=run out="" corpus="" targets="$all_targets" pack_dir="" copy_dir=""
while [ $# -gt 0 ]; do
  case "$1" in
    --bin-dir) bin_dir="$2"; shift 2 ;;
    --build) mode=build; shift; if [ $# -gt 0 ] && [[ "$1" != --* ]]; then copy_dir="$1"; shift; fi ;;
    --package) mode=package; pack_dir="$2"; shift 2 ;;
    --targets) targets="${2//,/ }"; shift 2 ;;
    --out) out="$2"; shift 2 ;;
    --corpus) corpus="$2"; shift 2 ;;
    --report) mode=report; out="$2"; shift 2 ;;
    -h|--help) sed -n '2,20p' "$0"; exit 0 ;;
    *) break ;;
  esac
done

build() {
  # libFuzzer's coverage instrumentation through stable rustc flags (what cargo-fuzz passes, minus
  # -Zsanitizer, which needs nightly). --target keeps the flags off build scripts and proc macros.
  local host
  host="$(rustc -vV | sed -n 's/^host: //p')"
  local flags="-Cpasses=sancov-module -Cllvm-args=-sanitizer-coverage-level=4"
  flags+=" -Cllvm-args=-sanitizer-coverage-inline-8bit-counters -Cllvm-args=-sanitizer-coverage-pc-table"
  flags+=" -Cllvm-args=-sanitizer-coverage-trace-compares --cfg fuzzing -Cforce-frame-pointers=yes"
  local bins=()
  for t in $targets; do bins+=(--bin "$t"); done
  (cd "$here" && RUSTFLAGS="$flags" CARGO_TARGET_DIR="$here/target" \
    cargo build --release --locked --target "$host" "${bins[@]}" >&2)
  bin_dir="$here/target/$host/release"
}

strip_into() {  # DIR: stripped copies of the built binaries
  mkdir -p "$1"
  for t in $targets; do
    cp "$bin_dir/$t" "$1/$t"
    strip "$1/$t" 2>/dev/null || echo "fuzz: strip not found; $1/$t left unstripped" >&2
  done
}

case "$mode" in
  build)
    build
    [ -n "$copy_dir" ] && strip_into "$copy_dir"
    exit 0 ;;
  package)
    build
    strip_into "$pack_dir/bin"
    mkdir -p "$pack_dir/corpus"
    for t in $targets; do rm -rf "$pack_dir/corpus/$t"; cp -r "$here/corpus/$t" "$pack_dir/corpus/$t"; done
    cp "$here/run.sh" "$pack_dir/run.sh"
    du -sh "$pack_dir" >&2
    exit 0 ;;
esac

if [ "$mode" = run ]; then
  [ $# -ge 1 ] || { echo "usage: $0 [--bin-dir DIR] SECONDS [JOBS]" >&2; exit 2; }
  seconds="$1" jobs="${2:-1}"
  [ -n "$bin_dir" ] || build
fi
[ -n "$corpus" ] || corpus="$here/corpus"
[ -n "$out" ] || out="$here/out"
mkdir -p "$out"
# The store target writes its three files per input: keep them in memory.
scratch="$(mktemp -d "$( [ -d /dev/shm ] && [ -w /dev/shm ] && echo /dev/shm || echo "${TMPDIR:-/tmp}")/mortar-fuzz.XXXXXX")"
trap 'rm -rf "$scratch"' EXIT

# One table row from a target's log and artifacts: TARGET SECONDS JOBS LOG ART.
row() {
  local t="$1" took="$2" jobs="$3" log="$4" art="$5" last execs cov ft corp crashes hangs ooms rate
  # Last status line: "#N ... cov: C ft: F corp: K ... exec/s: E ..." (plain and fork mode).
  last=$(grep -aE '^#[0-9]+' "$log" | tail -n 1 || true)
  field() { echo "$last" | grep -aEo "$1: [0-9]+" | awk '{print $2}' || true; }
  execs=$(sed -n 's/^stat::number_of_executed_units: *//p' "$log" | tail -n 1 || true)
  [ -n "$execs" ] || execs=$(echo "$last" | sed -nE 's/^#([0-9]+).*/\1/p')
  [ "$took" != "?" ] || took=$(grep -aEo 'Done [0-9]+ runs in [0-9]+ second' "$log" | awk '{print $5}' | tail -n 1 || true)
  cov=$(field cov) ft=$(field ft) corp=$(field corp)
  crashes=$(find "$art" -maxdepth 1 -name 'crash-*' 2>/dev/null | wc -l)
  hangs=$(find "$art" -maxdepth 1 -name 'timeout-*' 2>/dev/null | wc -l)
  ooms=$(find "$art" -maxdepth 1 \( -name 'oom-*' -o -name 'leak-*' \) 2>/dev/null | wc -l)
  execs=${execs:-0} took=${took:-0}
  rate=$(( took > 0 ? execs / took : execs ))
  echo "| $t | $took | $jobs | $execs | $rate | ${cov:-?} | ${ft:-?} | ${corp:-?} | $crashes | $hangs | $ooms |"
}

table_head() {
  echo
  echo "| target | seconds | jobs | executions | exec/s | cov | ft | corpus | crashes | hangs | ooms |"
  echo "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
}

main() {
  if [ "$mode" = report ]; then  # the table of an earlier run's logs (seconds from its log)
    table_head
    for t in $targets; do [ -f "$out/$t.log" ] && row "$t" "?" "?" "$out/$t.log" "$out/artifacts/$t"; done
    return 0
  fi
  local rows=() failed=0
  for t in $targets; do
    exe="$bin_dir/$t"
    [ -x "$exe" ] || { echo "fuzz: $exe not found" >&2; exit 2; }
    work="$out/corpus/$t" art="$out/artifacts/$t" log="$out/$t.log"
    mkdir -p "$work" "$art"
    seeds=()
    [ -d "$corpus/$t" ] && seeds=("$corpus/$t")
    # No -malloc_limit_mb: without AddressSanitizer libFuzzer cannot see single allocations;
    # the targets' own allocator aborts on one of more than 256 MiB (mortar_fuzz::LimitAlloc).
    args=(-max_total_time="$seconds" -timeout=10 -rss_limit_mb=2048
          -max_len=1048576 -print_final_stats=1 -artifact_prefix="$art/")
    [ -f "$corpus/$t.dict" ] && args+=(-dict="$corpus/$t.dict")
    if [ "$jobs" -gt 1 ]; then args+=(-fork="$jobs" -ignore_crashes=1 -ignore_ooms=1 -ignore_timeouts=1); fi
    echo "fuzz: $t for ${seconds}s (${jobs} job(s)), log $log" >&2
    start=$(date +%s)
    set +e
    TMPDIR="$scratch" RAYON_NUM_THREADS=1 "$exe" "${args[@]}" "$work" "${seeds[@]}" >"$log" 2>&1
    rc=$?
    set -e
    took=$(( $(date +%s) - start ))
    r=$(row "$t" "$took" "$jobs" "$log" "$art")
    rows+=("$r")
    if [ "$rc" -ne 0 ] || [ -n "$(ls -A "$art")" ]; then
      failed=1
      echo "fuzz: $t FAILED (exit $rc); inputs in $art, tail of $log:" >&2
      grep -aE 'panicked|huge allocation|ERROR|SUMMARY|Test unit written' "$log" | head -n 20 >&2 || true
      if [ -n "${FUZZ_PRINT_ARTIFACTS:-}" ]; then  # CI: the inputs, to save as fuzz/regressions/<target>/
        for f in "$art"/*; do
          [ -f "$f" ] && [ "$(stat -c %s "$f")" -le 65536 ] && echo "fuzz: $t input $(basename "$f") (base64): $(base64 -w0 "$f")" >&2
        done
      fi
    fi
  done
  table_head
  printf '%s\n' "${rows[@]}"
  return "$failed"
}

# Everything above is parsed before anything runs (an edit of this file during a run is harmless).
main
