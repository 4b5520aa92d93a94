#!/usr/bin/env bash
# Starts `isochron serve` (the simulated lab) on a free loopback port with a
# token, runs the browser checks against it, and stops it.
# Usage: web/e2e/run.sh PATH/TO/isochron
set -euo pipefail
bin=${1:?usage: run.sh PATH/TO/isochron}
here=$(cd "$(dirname "$0")/.." && pwd)
if [ ! -x "${CHROMIUM:-/usr/bin/chromium}" ]; then
  echo "browser tests: no Chromium at ${CHROMIUM:-/usr/bin/chromium} (make deps installs it)" >&2
  exit 1
fi
data=$(mktemp -d)
token="e2e-$RANDOM$RANDOM"
out="$data/serve.out"
# The FRI doctor's last report, as a user leaves one (nothing sends here: no_datagrams).
"$bin" fri doctor --listen 127.0.0.1:0 --seconds 0.3 --scan-ports none --data-dir "$data/db" >/dev/null 2>&1 || true
"$bin" serve --bind 127.0.0.1:0 --token "$token" --data-dir "$data/db" --web-dir "$here/dist" >"$out" 2>"$data/serve.err" &
pid=$!
cleanup() { kill "$pid" 2>/dev/null || true; wait "$pid" 2>/dev/null || true; rm -rf "$data"; }
trap cleanup EXIT
url=""
for _ in $(seq 1 300); do   # up to 30 s for the service to print its address
  url=$(grep -o 'http://[0-9.:]*/' "$out" | head -n1 || true)
  [ -n "$url" ] && break
  kill -0 "$pid" 2>/dev/null || { cat "$data/serve.err" >&2; echo "isochron serve exited" >&2; exit 1; }
  sleep 0.1
done
[ -n "$url" ] || { echo "isochron serve printed no address" >&2; exit 1; }
cd "$here"
node e2e/dashboard.mjs "$url" "$token"
