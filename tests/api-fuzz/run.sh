#!/usr/bin/env bash
# The schema-driven API fuzz test: starts `isochron serve` (the simulated lab)
# on a free loopback port with a token, runs schemathesis (installed by
# `make deps` in .venv) against its own OpenAPI document for a bounded time,
# and stops it. Checks: server errors, schema-violating requests accepted,
# schema-conforming requests refused, ignored authentication, status codes,
# content types and response bodies as documented. Any failure fails the test.
# Usage: tests/api-fuzz/run.sh PATH/TO/isochron [SECONDS]
set -euo pipefail
bin=${1:?usage: run.sh PATH/TO/isochron [SECONDS]}
seconds=${2:-${API_FUZZ_SECONDS:-60}}
root=$(cd "$(dirname "$0")/../.." && pwd)
st="$root/.venv/bin/schemathesis"
if [ ! -x "$st" ]; then
  echo "api fuzz: no schemathesis at $st (make deps installs it)" >&2
  exit 1
fi
# shellcheck source=../serve.sh
. "$root/tests/serve.sh"
serve_init fuzz
serve_start "$bin"
url=$serve_url token=$serve_token data=$serve_data pid=$serve_pid
# /api/stop is excluded: it is always accepted (any body, no token) by design
# and would abort the other operations' trials; tests/tests/e2e/http_api.rs covers it.
set +e
cd "$data"   # schemathesis keeps a cache folder in the working directory
"$st" --config-file "$root/tests/api-fuzz/schemathesis.toml" run "${url}api/openapi.json" \
  --url "${url%/}" \
  -H "Authorization: Bearer $token" \
  --exclude-path /api/stop --exclude-path /ws --exclude-path /ws/camera \
  --max-time "$seconds" --workers 1 --seed 24 \
  --phases examples,coverage,fuzzing \
  --request-timeout 10 \
  --suppress-health-check all \
  --output-truncate true 2>&1 | tee "$data/schemathesis.log"
rc=${PIPESTATUS[0]}
set -e
kill -0 "$pid" 2>/dev/null || { echo "isochron serve died during the fuzz run" >&2; cat "$data/serve.err" >&2; exit 1; }
if [ "$rc" -ne 0 ]; then
  echo "api fuzz: FAILED (schemathesis exit $rc)"
  echo "api fuzz: 0 passed, 1 failed"
  exit 1
fi
echo "api fuzz: 1 passed, 0 failed"
