#!/usr/bin/env bash
# A mortar build on a Slurm cluster: `mortar plan` here, one array task per job
# (`sbatch --array=0-$((N-1))`), and the merge as a job that waits for all of them
# (`--dependency=afterok`). Inputs, binary and OUT_DIR must be on a filesystem every node sees.
#   deploy/slurm/submit.sh N OUT_DIR INPUT...      (the store appears at OUT_DIR/store)
# Environment:
#   MORTAR       the mortar binary (default: the one on PATH)
#   MEMORY       --memory of each job (default 8G); ask Slurm for a little more (SBATCH_ARGS)
#   CPUS         cores per job (default 16)
#   LEAF         --leaf-capacity (default mortar's)
#   SBATCH_ARGS  more sbatch options for every job: --partition, --account, --mem, --time...
#   WAIT=1       return when the merge has finished (sbatch --wait), with its exit status
# A job that fails can be submitted again alone (`sbatch --array=I ...` or `mortar build
# --plan OUT_DIR/plan.json --job I -o OUT_DIR/parts/part-I`); the merge refuses an incomplete
# set of parts.
set -euo pipefail
[ $# -ge 3 ] || { sed -n 2,16p "$0"; exit 2; }
n=$1; out=$(realpath -m "$2"); shift 2
mortar=$(realpath "${MORTAR:-$(command -v mortar)}")
mkdir -p "$out/parts" "$out/logs"
leaf=(); [ -n "${LEAF:-}" ] && leaf=(--leaf-capacity "$LEAF")
"$mortar" plan "$@" --jobs "$n" -o "$out/plan.json" "${leaf[@]}"
# shellcheck disable=SC2086
array=$(sbatch --parsable --array=0-$((n - 1)) --cpus-per-task="${CPUS:-16}" --job-name=mortar-job \
  --output="$out/logs/job-%a.log" ${SBATCH_ARGS:-} \
  --wrap "'$mortar' build --plan '$out/plan.json' --job \$SLURM_ARRAY_TASK_ID -o '$out/parts/part-'\$(printf %05d \$SLURM_ARRAY_TASK_ID) --memory ${MEMORY:-8G} --threads \$SLURM_CPUS_PER_TASK --json")
wait=(); [ "${WAIT:-0}" = 1 ] && wait=(--wait)
echo "plan $out/plan.json; jobs: array $array (0-$((n - 1))); the merge waits for them" >&2
# shellcheck disable=SC2086
sbatch --parsable "${wait[@]}" --dependency=afterok:"$array" --kill-on-invalid-dep=yes --job-name=mortar-merge \
  --cpus-per-task=1 --output="$out/logs/merge.log" ${SBATCH_ARGS:-} \
  --wrap "'$mortar' merge '$out'/parts/part-* -o '$out/store' --json"
