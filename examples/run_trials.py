#!/usr/bin/env python3
"""Run a batch of trials on an isochron lab over REST and print what came of it.

Starts one run (POST /api/runs) of N trials at each distance, in turn, waits
for it on GET /api/runs/{id} (no retrying of refusals: the run starts each
trial when the lab can take it), prints a table per distance (trials,
successes, timing error p50 / p95) and saves each trial's MCAP recording.
Standard library only.

    python3 examples/run_trials.py --url http://127.0.0.1:8080 --token TOKEN \
        --n 20 --distance 0.50 0.70 --out trials/
"""
import argparse
import json
import os
import statistics
import sys
import time
import urllib.error
import urllib.request


def call(base, token, method, path, body=None):
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(base.rstrip("/") + path, data=data, method=method)
    req.add_header("Content-Type", "application/json")
    if token:
        req.add_header("Authorization", "Bearer " + token)
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            raw = r.read()
            return r.status, (json.loads(raw) if r.headers.get_content_type() == "application/json" else raw)
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read() or b"null")


def pct(values, q):
    """numpy's default percentile: linear between closest ranks."""
    if not values:
        return None
    s = sorted(values)
    pos = q * (len(s) - 1)
    lo = int(pos)
    hi = min(lo + 1, len(s) - 1)
    return s[lo] + (s[hi] - s[lo]) * (pos - lo)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--url", default="http://127.0.0.1:8080")
    ap.add_argument("--token", default=os.environ.get("ISOCHRON_TOKEN"))
    ap.add_argument("--n", type=int, default=20, help="trials per distance")
    ap.add_argument("--distance", type=float, nargs="+", default=[0.50, 0.70], metavar="M")
    ap.add_argument("--movement-time", type=float, default=None, metavar="S")
    ap.add_argument("--out", default="trials", help="folder for the MCAP recordings")
    ap.add_argument("--timeout", type=float, default=3600.0, metavar="S")
    a = ap.parse_args()

    body = {"n": a.n * len(a.distance), "distance_m": a.distance}
    if a.movement_time is not None:
        body["movement_time_s"] = a.movement_time
    code, started = call(a.url, a.token, "POST", "/api/runs", body)
    if code != 202:
        sys.exit(f"run refused: {code} {started}")
    run = started["id"]
    print(f"run {run}: {body['n']} trials at {', '.join(f'{d:.2f}' for d in a.distance)} m", flush=True)
    deadline = time.monotonic() + a.timeout
    shown = 0
    while True:
        _, r = call(a.url, a.token, "GET", f"/api/runs/{run}")
        if r["finished"] > shown:
            shown = r["finished"]
            print(f"  {shown}/{r['n']} finished, {r['successes']} successes", flush=True)
        if r["status"] != "running":
            break
        if time.monotonic() > deadline:
            call(a.url, a.token, "DELETE", f"/api/runs/{run}")
            sys.exit(f"run {run} not finished after {a.timeout} s: stopped")
        time.sleep(0.5)
    if r["status"] != "done":
        sys.exit(f"run {run} {r['status']}: {r.get('message')}")

    os.makedirs(a.out, exist_ok=True)
    rows = {}
    for tid in r["trial_ids"]:
        _, t = call(a.url, a.token, "GET", f"/api/trials/{tid}")
        rows.setdefault(round(t["distance_m"], 3), []).append(t)
        code, mcap = call(a.url, a.token, "GET", f"/api/trials/{tid}/recording.mcap")
        if code == 200:
            with open(os.path.join(a.out, f"{tid}.mcap"), "wb") as f:
                f.write(mcap)
    print(f"{'distance m':>10} {'trials':>6} {'success':>7} {'timing p50 ms':>13} {'timing p95 ms':>13}")
    for d in sorted(rows):
        ts = rows[d]
        ok = sum(1 for t in ts if t.get("success") is True)
        timing = [abs(t["timing_error_ms"]) for t in ts if t.get("timing_error_ms") is not None]
        fmt = lambda v: "-" if v is None else f"{v:.2f}"
        print(f"{d:>10.2f} {len(ts):>6} {ok:>7} {fmt(pct(timing, 0.5)):>13} {fmt(pct(timing, 0.95)):>13}")
    lo, hi = r["success_ci95"]
    print(f"all: {r['successes']}/{r['finished']} successes (95% interval {lo:.2f}..{hi:.2f}); "
          f"MCAPs in {a.out}/")
    saved = len([f for f in os.listdir(a.out) if f.endswith(".mcap")])
    if saved < len(r["trial_ids"]):
        sys.exit(f"only {saved} of {len(r['trial_ids'])} recordings saved")


if __name__ == "__main__":
    main()
