#!/usr/bin/env bash
# The same as run_trials.py with curl: one trial at 0.70 m in 2.0 s, then a
# run of N trials at 0.50 and 0.70 m, waiting on the lab's own readiness and
# the run's status (never retrying refusals). Needs curl and python3 (for JSON).
# Usage: examples/run_trials.sh URL [TOKEN] [N]
set -euo pipefail
url=${1:-http://127.0.0.1:8080}; url=${url%/}
token=${2:-${ISOCHRON_TOKEN:-}}
n=${3:-20}
auth=(); [ -n "$token" ] && auth=(-H "Authorization: Bearer $token")
api() { curl -sS --fail-with-body -H 'Content-Type: application/json' "${auth[@]}" "$@"; }
field() { python3 -c "import json,sys; print(json.load(sys.stdin)$1)"; }

# Wait until the lab would take a trial (GET /api/health says why not).
until [ "$(api "$url/api/health" | field "['ready']")" = True ]; do sleep 0.5; done
id=$(api -X POST "$url/api/trials" -d '{"distance_m": 0.70, "movement_time_s": 2.0}' | field "['id']")
echo "trial $id: 0.70 m in 2.0 s"
until [ "$(api "$url/api/trials/$id" | field "['status']")" != running ]; do sleep 0.5; done
api "$url/api/trials/$id" | field "['reason']"

run=$(api -X POST "$url/api/runs" -d "{\"n\": $((2 * n)), \"distance_m\": [0.50, 0.70]}" | field "['id']")
echo "run $run: $((2 * n)) trials at 0.50 and 0.70 m"
until [ "$(api "$url/api/runs/$run" | field "['status']")" != running ]; do sleep 1; done
api "$url/api/runs/$run" | python3 -c "$(cat <<'PY'
import json, sys
r = json.load(sys.stdin)
lo, hi = r["success_ci95"]
print(f"run {r['id']} {r['status']}: {r['successes']}/{r['finished']} successes "
      f"(95% interval {lo:.2f}..{hi:.2f}), timing p50 {r['timing_error_ms_p50']} ms, "
      f"p95 {r['timing_error_ms_p95']} ms, trials {r['trial_ids']}")
sys.exit(0 if r["status"] == "done" and r["finished"] == r["n"] else 1)
PY
)"
