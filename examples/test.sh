#!/usr/bin/env bash
# `make test`'s run of the example scripts: `isochron serve` (the simulated
# lab) on a free loopback port with a token, then run_trials.py and
# run_trials.sh against it with N trials a distance (default 1).
# Usage: examples/test.sh PATH/TO/isochron [N]
set -euo pipefail
bin=${1:?usage: test.sh PATH/TO/isochron [N]}
n=${2:-1}
here=$(cd "$(dirname "$0")" && pwd)
data=$(mktemp -d)
token="ex-$RANDOM$RANDOM"
"$bin" serve --bind 127.0.0.1:0 --token "$token" --data-dir "$data/db" >"$data/serve.out" 2>"$data/serve.err" &
pid=$!
cleanup() { kill "$pid" 2>/dev/null || true; wait "$pid" 2>/dev/null || true; rm -rf "$data"; }
trap cleanup EXIT
url=""
for _ in $(seq 1 300); do   # up to 30 s for the service to print its address
  url=$(grep -o 'http://[0-9.:]*/' "$data/serve.out" | head -n1 || true)
  [ -n "$url" ] && break
  kill -0 "$pid" 2>/dev/null || { cat "$data/serve.err" >&2; echo "isochron serve exited" >&2; exit 1; }
  sleep 0.1
done
[ -n "$url" ] || { echo "isochron serve printed no address" >&2; exit 1; }
fails=0
if python3 "$here/run_trials.py" --url "$url" --token "$token" --n "$n" --out "$data/mcap" --timeout 600; then
  n_mcap=$(ls "$data/mcap"/*.mcap | wc -l)
  [ "$n_mcap" -eq $((2 * n)) ] || { echo "examples: $n_mcap MCAPs saved, $((2 * n)) expected"; fails=$((fails + 1)); }
else
  fails=$((fails + 1))
fi
"$here/run_trials.sh" "$url" "$token" "$n" || fails=$((fails + 1))
echo "examples: $((2 - fails)) passed, $fails failed"
[ "$fails" -eq 0 ]
