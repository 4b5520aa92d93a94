#!/bin/sh
# One shard of an `isochron trials` run, as a cluster task runs it.
#
# The shard's index comes from the scheduler: JOB_COMPLETION_INDEX (a Kubernetes
# Indexed Job), SLURM_ARRAY_TASK_ID (a Slurm job array), or SHARD_INDEX (by hand);
# the rest from the environment:
#   SCENARIO     scenario file (required)
#   N            trials in the whole run (required)
#   SHARD_COUNT  shards in the whole run (required; Slurm: SLURM_ARRAY_TASK_COUNT)
#   SEED         the run's seed (default 1)
#   BLOCK        trials per lab day (default 100; at least N / SHARD_COUNT days are needed)
#   OUT_DIR      where shard-<index>.json is written (default .)
#   ISOCHRON     the release binary (default: isochron on PATH)
#   EXTRA_ARGS   more `isochron trials` arguments, e.g. "--calibration cal.toml"
# The output appears only when the shard succeeded (written to a temporary
# name, then renamed), so `isochron merge OUT_DIR/shard-*.json` never reads half a file.
set -eu
index=${SHARD_INDEX:-${JOB_COMPLETION_INDEX:-${SLURM_ARRAY_TASK_ID:-}}}
if [ -z "$index" ]; then
  echo "run-shard.sh: no shard index (JOB_COMPLETION_INDEX, SLURM_ARRAY_TASK_ID or SHARD_INDEX)" >&2
  exit 2
fi
count=${SHARD_COUNT:-${SLURM_ARRAY_TASK_COUNT:-}}
: "${count:?run-shard.sh: SHARD_COUNT is not set}"
: "${SCENARIO:?run-shard.sh: SCENARIO is not set}"
: "${N:?run-shard.sh: N is not set}"
out=${OUT_DIR:-.}
mkdir -p "$out"
tmp="$out/.shard-$index.json.$$"
# shellcheck disable=SC2086 # EXTRA_ARGS is a list of words on purpose
"${ISOCHRON:-isochron}" trials --scenario "$SCENARIO" --n "$N" --seed "${SEED:-1}" \
  --block "${BLOCK:-100}" --shard "$index/$count" --json ${EXTRA_ARGS:-} > "$tmp"
mv "$tmp" "$out/shard-$index.json"
