#!/bin/bash
# Queues the shards (trials-array.sbatch) and, after all of them succeeded, the
# merge: results/summary.json is then what `isochron trials` without --shard prints.
# Run from the repository root after `make release`.
set -euo pipefail
mkdir -p results
jobid=$(sbatch --parsable deploy/slurm/trials-array.sbatch)
sbatch --dependency="afterok:${jobid}" --job-name=isochron-merge --output=results/merge.log \
  --wrap "${ISOCHRON:-target/release/isochron} merge results/shard-*.json > results/summary.json"
echo "queued shards ${jobid} and their merge; the summary will be results/summary.json"
