#!/usr/bin/env bash
# Starts `isochron serve` (the simulated lab: a truthful world behind a real
# lab's interfaces; its truth file in the data folder) on a free loopback port with a
# token, runs the browser checks against it, and stops it.
# Usage: web/e2e/run.sh PATH/TO/isochron
set -euo pipefail
bin=${1:?usage: run.sh PATH/TO/isochron}
here=$(cd "$(dirname "$0")/.." && pwd)
if [ ! -x "${CHROMIUM:-/usr/bin/chromium}" ]; then
  echo "browser tests: no Chromium at ${CHROMIUM:-/usr/bin/chromium} (make deps installs it)" >&2
  exit 1
fi
# shellcheck source=../../tests/serve.sh
. "$here/../tests/serve.sh"
serve_init e2e
data=$serve_data
# The FRI doctor's last report, as a user leaves one (nothing sends here: no_datagrams).
"$bin" fri doctor --listen 127.0.0.1:0 --seconds 0.3 --scan-ports none --data-dir "$data/db" >/dev/null 2>&1 || true
serve_start "$bin" --web-dir "$here/dist"
url=$serve_url token=$serve_token
cd "$here"
ISOCHRON_DATA_DIR="$data/db" node e2e/dashboard.mjs "$url" "$token"
