#!/usr/bin/env bash
# `make stress-test`: `CI=true make test` RUNS times in a row (default 5) with
# `stress-ng --cpu 2` loading both cores beside it: the proof that the suite
# is never red on a sound, busy machine (issue 34). Each run's output goes to
# reports/stress/run-K.log; a table of exit codes and wall times is printed
# and written to reports/stress/summary.md. Exits non-zero if any run failed.
set -u
RUNS=${1:-5}
CPUS=${STRESS_CPUS:-2}
cd "$(dirname "$0")/../.."
command -v stress-ng >/dev/null || { echo "stress-test: no stress-ng (make deps installs it)"; exit 1; }
out=reports/stress
mkdir -p "$out"
rev=$(git rev-parse --short HEAD)$(git diff --quiet HEAD || echo "+dirty")
summary="$out/summary.md"
{
  echo "# \`CI=true make test\` under \`stress-ng --cpu $CPUS\`"
  echo
  echo "Tree $rev, $(nproc) cores, $(date -u +%Y-%m-%dT%H:%MZ)."
  echo
  echo "| run | exit | wall (s) | failed checks |"
  echo "|---|---|---|---|"
} > "$summary"
failed=0
for k in $(seq 1 "$RUNS"); do
  stress-ng --cpu "$CPUS" --quiet &
  load=$!
  t0=$(date +%s)
  CI=true make test > "$out/run-$k.log" 2>&1
  rc=$?
  t1=$(date +%s)
  kill "$load" 2>/dev/null; wait "$load" 2>/dev/null
  fails=$(grep -E '^(FAIL|test .* FAILED|---- )|panicked at|Error [0-9]+$' "$out/run-$k.log" | head -5 | tr '\n' ';' | sed 's/|/\\|/g')
  echo "| $k | $rc | $((t1 - t0)) | ${fails:--} |" | tee -a "$summary"
  [ "$rc" = 0 ] || failed=$((failed + 1))
done
echo
echo "stress-test: $((RUNS - failed)) of $RUNS runs green ($summary)"
[ "$failed" = 0 ]
