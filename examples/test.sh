#!/usr/bin/env bash
# `make test`'s run of the example scripts: `isochron serve` (the simulated
# lab) on a free loopback port with a token, then run_trials.py and
# run_trials.sh against it with N trials a distance (default 1).
# Usage: examples/test.sh PATH/TO/isochron [N]
set -euo pipefail
bin=${1:?usage: test.sh PATH/TO/isochron [N]}
n=${2:-1}
here=$(cd "$(dirname "$0")" && pwd)
# shellcheck source=../tests/serve.sh
. "$here/../tests/serve.sh"
serve_init ex
serve_start "$bin"
url=$serve_url token=$serve_token data=$serve_data
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
