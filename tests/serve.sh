# shellcheck shell=bash
# `isochron serve` for the scripts that test against a running service
# (examples/test.sh, tests/api-fuzz/run.sh, web/e2e/run.sh). Source it, then:
#
#   serve_init PREFIX        a fresh data folder and token; the service stops and
#                            the folder goes at exit
#   serve_start BIN [ARGS]   `BIN serve` (the simulated lab) on a free loopback port
#                            with that token and data, ARGS added; waits up to 30 s
#                            for it to print its address (fails, with its stderr,
#                            when it exits first or prints none)
#   serve_alive              whether it still runs
#
# and reads serve_data (the folder; the service's data is in $serve_data/db),
# serve_token, serve_pid and serve_url (http://127.0.0.1:PORT/).

serve_init() {
  serve_data=$(mktemp -d)
  serve_token="${1:?serve_init PREFIX}-$RANDOM$RANDOM"
  serve_pid=""
  serve_url=""
  trap serve_stop EXIT
}

serve_stop() {
  if [ -n "${serve_pid:-}" ]; then
    kill "$serve_pid" 2>/dev/null || true
    wait "$serve_pid" 2>/dev/null || true
  fi
  rm -rf "${serve_data:?}"
}

serve_alive() {
  kill -0 "$serve_pid" 2>/dev/null
}

serve_start() {
  local bin=${1:?serve_start BIN [ARGS]}
  shift
  "$bin" serve --bind 127.0.0.1:0 --token "$serve_token" --data-dir "$serve_data/db" "$@" \
    >"$serve_data/serve.out" 2>"$serve_data/serve.err" &
  serve_pid=$!
  serve_url=""
  local _
  for _ in $(seq 1 600); do   # up to 60 s for the service (its world first) to print its address
    serve_url=$(grep -o 'http://[0-9.:]*/' "$serve_data/serve.out" | head -n1 || true)
    [ -n "$serve_url" ] && return 0
    serve_alive || { cat "$serve_data/serve.err" >&2; echo "isochron serve exited" >&2; exit 1; }
    sleep 0.1
  done
  echo "isochron serve printed no address" >&2
  exit 1
}
