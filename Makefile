# isochron: the two commands of the README are `make run` and `make test`.
# Everything they need is installed here (`make deps`), never by hand.

SHELL := /bin/bash
.SHELLFLAGS := -eu -o pipefail -c
.DEFAULT_GOAL := help

CARGO ?= cargo
BIND ?= 127.0.0.1:8080

# System packages the build and the tests need (Debian names).
APT_PKGS := libopencv-dev clang libclang-dev pkg-config \
            gcc-avr avr-libc binutils-avr libsimavr-dev \
            chromium python3 python3-venv curl stress-ng
# Each stage of `make test` notes when it starts in target/stages.log; `make
# test` ends with the table of how long each took (serial make: a stage lasts
# until the next one starts).
STAGES_LOG := target/stages.log
STAGE = @mkdir -p target && echo "$@ $$(date +%s)" >> $(STAGES_LOG)
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: stages-begin stress-test demo eval-world test-build test-examples soak fuzz-lifecycle peer-deps test-core py-deps mcap-py-deps test-api-fuzz test-browser eval envelope help deps apt-deps web-deps fuzz-deps fuzz fuzz-smoke fuzz-seeds web run test test-rust test-web lint bench build release firmware types

help:
	@echo "make run    install what is missing, build, and serve the simulated lab on http://$(BIND)/"
	@echo "make test   install what is missing, then formatting, lints and every test"
	@echo "make demo   serve the simulated lab in demo mode: trials run unattended, the kiosk page at http://$(BIND)/demo"
	@echo "make bench  criterion benches and 'isochron bench'"
	@echo "make eval   trials across distances and movement times; writes reports/eval/report.md"
	@echo "make envelope  the reality lab's robustness envelope per world factor; writes reports/eval/envelope.md (hours)"
	@echo "make fuzz   each FRI fuzz target for FUZZ_SECONDS (default 60; fuzz/README.md)"
	@echo "make stress-test  CI=true make test STRESS_RUNS times (default 5) beside stress-ng --cpu 2; writes reports/stress/summary.md"
	@echo "make deps   install missing system, npm and cargo packages (idempotent)"
	@echo "make types  regenerate web/src/generated/types.ts from the Rust types (ts-rs)"

## deps: install only what is missing.
deps: apt-deps web-deps fuzz-deps py-deps mcap-py-deps
	$(STAGE)

apt-deps:
	@missing=""; \
	for p in $(APT_PKGS); do \
	  dpkg-query -W -f='$${Status}' "$$p" 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  echo "make deps: installing$$missing"; \
	  $(SUDO) apt-get update -qq; \
	  DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq --no-install-recommends $$missing; \
	fi

# The MCAP test's second, independent reader (the `mcap` package from PyPI, for
# the python3 the tests call: tests/py/mcap_summary.py).
PY_MCAP_VERSION := 1.6.0
mcap-py-deps:
	@if ! python3 -c 'import mcap, sys; sys.exit(mcap.__version__ != "$(PY_MCAP_VERSION)")' 2>/dev/null; then \
	  echo "make deps: installing the mcap Python package $(PY_MCAP_VERSION)"; \
	  python3 -m pip install --quiet --disable-pip-version-check "mcap==$(PY_MCAP_VERSION)"; \
	fi

web-deps: web/node_modules/.package-lock.json

web/node_modules/.package-lock.json: web/package.json web/package-lock.json
	cd web && npm ci --no-audit --no-fund
	@touch $@

## py-deps: schemathesis (the schema-driven API fuzz test) in a project-local venv.
PY ?= python3
VENV := .venv
SCHEMATHESIS_VERSION := 4.32.5

py-deps: $(VENV)/.schemathesis-$(SCHEMATHESIS_VERSION)

$(VENV)/.schemathesis-$(SCHEMATHESIS_VERSION):
	@[ -x $(VENV)/bin/python ] || $(PY) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --disable-pip-version-check "schemathesis==$(SCHEMATHESIS_VERSION)"
	@touch $@

## fuzz: the FRI fuzz targets (fuzz/README.md). Stable Rust: no sanitizer, debug assertions on.
CARGO_FUZZ_VERSION := 0.13.2
FUZZ_TARGETS := monitoring_decode command_decode client_on_datagram sim_on_reply
FUZZ_SECONDS ?= 60
FUZZ_SMOKE_SECONDS ?= 10

fuzz-deps:
	@if ! $(CARGO) fuzz --version 2>/dev/null | grep -qx "cargo-fuzz $(CARGO_FUZZ_VERSION)"; then \
	  echo "make deps: installing cargo-fuzz $(CARGO_FUZZ_VERSION)"; \
	  $(CARGO) install --locked cargo-fuzz --version $(CARGO_FUZZ_VERSION); \
	fi

# $(call fuzz_run,SECONDS,BUILD): each target for SECONDS on fuzz/corpus/T (new inputs) and
# fuzz/seeds/T (the committed seeds); a crash fails with the log's tail and the input
# saved under fuzz/artifacts/T/. BUILD is empty (release: the fuzzing runs) or `--dev`
# (the smoke: fuzz/Cargo.toml's dev profile, incremental, a fraction of the build time).
define fuzz_run
	$(CARGO) fuzz build $(2) --sanitizer none
	@mkdir -p target
	@for t in $(FUZZ_TARGETS); do \
	  mkdir -p fuzz/corpus/$$t; \
	  log=target/fuzz-$$t.log; \
	  if ! $(CARGO) fuzz run $(2) --sanitizer none $$t fuzz/corpus/$$t fuzz/seeds/$$t -- \
	      -max_total_time=$(1) -print_final_stats=1 >$$log 2>&1; then \
	    tail -n 40 $$log; echo "fuzz $$t: FAILED (input in fuzz/artifacts/$$t/, log $$log)"; exit 1; \
	  fi; \
	  echo "fuzz $$t: $$(sed -n 's/^stat::number_of_executed_units: *//p' $$log) runs in $(1) s, no crash"; \
	done
endef

fuzz: fuzz-deps fuzz-lifecycle
	$(call fuzz_run,$(FUZZ_SECONDS),)

## fuzz-lifecycle: the lab's lifecycle (no trial record lost): LIFECYCLE_SEQUENCES random
## command sequences on the virtual clock, then LIFECYCLE_SERVED_S seconds of random REST
## commands against a served lab over real sockets (`make test` runs short versions).
LIFECYCLE_SEQUENCES ?= 2000
LIFECYCLE_SERVED_S ?= 180
fuzz-lifecycle: firmware
	ISOCHRON_LIFECYCLE_SEQUENCES=$(LIFECYCLE_SEQUENCES) $(CARGO) test --release -p rt-core --lib \
	  sim::lifecycle::tests::no_command_sequence_loses_a_trial_record -- --nocapture
	$(CARGO) build --bin isochron
	ISOCHRON_LIFECYCLE_SERVED_S=$(LIFECYCLE_SERVED_S) $(CARGO) test -p isochron-tests --test e2e \
	  lifecycle_served::random_rest_sequences_lose_no_trial_record -- --nocapture

# The smoke runs the targets side by side (a quarter of the wall time; each
# gets fewer runs, and the smoke asks only that none crashes); `make fuzz` one
# after another, each on a whole core.
fuzz-smoke: fuzz-deps
	$(STAGE)
	$(CARGO) fuzz build --dev --sanitizer none
	@mkdir -p target
	@for t in $(FUZZ_TARGETS); do \
	  mkdir -p fuzz/corpus/$$t; \
	  $(CARGO) fuzz run --dev --sanitizer none $$t fuzz/corpus/$$t fuzz/seeds/$$t -- \
	    -max_total_time=$(FUZZ_SMOKE_SECONDS) -print_final_stats=1 >target/fuzz-$$t.log 2>&1 & \
	  echo $$! > target/fuzz-$$t.pid; \
	done; \
	failed=0; \
	for t in $(FUZZ_TARGETS); do \
	  log=target/fuzz-$$t.log; \
	  if wait $$(cat target/fuzz-$$t.pid); then \
	    echo "fuzz $$t: $$(sed -n 's/^stat::number_of_executed_units: *//p' $$log) runs in $(FUZZ_SMOKE_SECONDS) s, no crash"; \
	  else \
	    tail -n 40 $$log; echo "fuzz $$t: FAILED (input in fuzz/artifacts/$$t/, log $$log)"; failed=1; \
	  fi; \
	done; \
	exit $$failed

## fuzz-seeds: regenerate the committed seed corpus from real sessions.
fuzz-seeds:
	$(CARGO) run --manifest-path fuzz/Cargo.toml --example seeds -- fuzz/seeds

## firmware: the magnet firmware (.elf/.hex for the Uno) and its simavr host for the tests.
FW_DIR := firmware/magnet
FW_BUILD := $(FW_DIR)/build
AVR_CFLAGS := -mmcu=atmega328p -DF_CPU=16000000UL -Os -Wall -Wextra -Werror -std=gnu99
SIM_FLAGS := -I/usr/include/simavr -I/usr/include/simavr/parts -lsimavr -lsimavrparts -lpthread -lutil

firmware: apt-deps $(FW_BUILD)/magnet.hex $(FW_BUILD)/magnet-sim

$(FW_BUILD)/magnet.elf: $(FW_DIR)/magnet.c
	@mkdir -p $(FW_BUILD)
	avr-gcc $(AVR_CFLAGS) -o $@ $<

$(FW_BUILD)/magnet.hex: $(FW_BUILD)/magnet.elf
	avr-objcopy -O ihex -R .eeprom $< $@
	@avr-size $<

$(FW_BUILD)/magnet-sim: $(FW_DIR)/sim_host.c
	@mkdir -p $(FW_BUILD)
	gcc -O2 -Wall -Wextra -Werror -o $@ $< $(SIM_FLAGS)

## web: the dashboard, built into web/dist (served by `isochron serve`).
web: web-deps
	$(STAGE)
	cd web && npm run build

build: deps
	$(CARGO) build --workspace

release: deps
	$(CARGO) build --release --bin isochron

run: deps firmware web release
	@echo "isochron: the simulated lab and dashboard at http://$(BIND)/ (Ctrl-C stops)"
	"$${CARGO_TARGET_DIR:-target}/release/isochron" serve --bind $(BIND)

## demo: the simulated lab in demo mode (a trial every DEMO_INTERVAL_S seconds,
## unattended); the kiosk page for a screen in the hall at /demo.
DEMO_INTERVAL_S ?= 10
demo: deps firmware web release
	@echo "isochron demo: the kiosk page at http://$(BIND)/demo, the dashboard at http://$(BIND)/ (Ctrl-C stops)"
	"$${CARGO_TARGET_DIR:-target}/release/isochron" serve --bind $(BIND) --demo --demo-interval-s $(DEMO_INTERVAL_S)

lint: deps
	$(STAGE)
	$(CARGO) fmt --all -- --check
	$(CARGO) clippy --workspace --all-targets -- -D warnings

test-web: web
	$(STAGE)
	cd web && npm run typecheck && npm test

## test-rust: every Rust test. The unit tests (in-process, CPU-bound) run as
## many at a time as the harness likes (one per core); the integration test
## binaries TEST_THREADS (default 4) at a time. The end-to-end binary's tests
## (tests/tests/e2e) mostly wait on lab processes, trials in wall-clock time
## and sockets (1 min 47 s of CPU in 5 min 30 s one at a time): 330 s one at a
## time, 164 s two, 98 s four on a quiet machine; 119 s four beside
## `stress-ng --cpu 2`. The world binary's tests run one at a time whatever
## this says (a world and its lab load both cores: `ONE_LAB`). (The three runs
## select targets only: one build graph, nothing rebuilt.)
TEST_THREADS ?= 4
test-rust: deps firmware
	$(STAGE)
	@mkdir -p target
	{ $(CARGO) test --workspace --lib --bins && \
	  $(CARGO) test --workspace --test '*' -- --test-threads $(TEST_THREADS) && \
	  $(CARGO) test --workspace --doc; } 2>&1 | tee target/test-rust.log
	@awk '/^test result:/ {p += $$4; f += $$6} END {printf "rust: %d passed, %d failed\n", p, f}' target/test-rust.log

## test-core: the core builds and runs with Rust alone (no OpenCV, libclang or
## libudev: rt-core without its default features `opencv` and `serial`): its
## normal dependency tree has none of them, and the virtual-clock trial driver's
## allocation test passes in that build.
## Outside CI (the dev loop) that build is checked (`cargo check`), not linked and run:
## the same allocation test runs with the default features in test-rust.
test-core:
	$(STAGE)
	@if $(CARGO) tree -p rt-core --no-default-features -e normal --prefix none \
	    | grep -E '^(opencv|clang-sys|libudev-sys) '; then \
	  echo "rt-core --no-default-features depends on a C/C++ library (above)"; exit 1; fi
	@if [ "$${CI:-}" = true ]; then \
	  $(CARGO) test -p rt-core --no-default-features --test control_step_no_alloc; \
	else \
	  $(CARGO) check -p rt-core --no-default-features --lib --tests; \
	fi

## test-browser: the dashboard in headless Chromium against `isochron serve` (the simulated lab).
## test-build: every test binary and the `isochron` binary they use, in one build
## graph (`cargo build --bin` alone resolves other features for the dependencies
## and would build OpenCV's bindings a second time); the browser, API-fuzz and
## example runs use that binary.
test-build: deps firmware
	$(STAGE)
	$(CARGO) test --workspace --no-run

# The soak in `make test` checks the heap for 30 s and reports the frame rate;
# `make soak` runs it for SOAK_S (default 300) and gates the frame rate too.
# The demo page's short test (>= 2 unattended trials, a pause, a restart) runs
# here too; its 10-minute soak only in `make soak`.
test-browser: web test-build
	$(STAGE)
	ISOCHRON_SOAK_S=$${ISOCHRON_SOAK_S:-30} web/e2e/run.sh "$${CARGO_TARGET_DIR:-target}/debug/isochron"
	node web/e2e/demo.mjs "$${CARGO_TARGET_DIR:-target}/debug/isochron"

# Then the demo page unattended for DEMO_SOAK_S (default 600): >= 40 trials,
# the heap, no console error, fps; it saves docs/demo.png.
SOAK_S ?= 300
DEMO_SOAK_S ?= 600
soak: firmware web
	$(CARGO) build --bin isochron
	ISOCHRON_SOAK_S=$(SOAK_S) ISOCHRON_SOAK_FPS_MIN=30 web/e2e/run.sh "$${CARGO_TARGET_DIR:-target}/debug/isochron"
	ISOCHRON_DEMO_SOAK_S=$(DEMO_SOAK_S) ISOCHRON_SOAK_FPS_MIN=30 ISOCHRON_DEMO_SCREENSHOT=docs/demo.png \
	  node web/e2e/demo.mjs "$${CARGO_TARGET_DIR:-target}/debug/isochron"

## test-api-fuzz: schemathesis against `isochron serve`'s own OpenAPI document, for
## API_FUZZ_SECONDS (default 30: its coverage phase, every operation, takes 4 s, then
## fuzzing, about 3,000 cases in all on the 2-core VM; 60 s gave 5,400): 0 failures
## (tests/api-fuzz/run.sh). A longer run: `make test-api-fuzz API_FUZZ_SECONDS=600`.
API_FUZZ_SECONDS ?= 30
test-api-fuzz: py-deps test-build
	$(STAGE)
	tests/api-fuzz/run.sh "$${CARGO_TARGET_DIR:-target}/debug/isochron" $(API_FUZZ_SECONDS)

## test-examples: examples/run_trials.py and run_trials.sh against `isochron serve`
## (the simulated lab), one trial a distance each (examples/test.sh); then the
## core's own examples (rt-core/examples: predict a pass, plan a timed motion,
## decode an FRI datagram), built by test-build, each exiting non-zero when
## what it shows does not hold.
CORE_EXAMPLES := predict_pass plan_motion decode_fri
test-examples: test-build
	$(STAGE)
	examples/test.sh "$${CARGO_TARGET_DIR:-target}/debug/isochron" 1
	@for e in $(CORE_EXAMPLES); do \
	  echo "== rt-core example $$e"; \
	  "$${CARGO_TARGET_DIR:-target}/debug/examples/$$e" || exit 1; \
	done

## stress-test: `CI=true make test` STRESS_RUNS times (default 5) beside
## `stress-ng --cpu 2`; writes reports/stress/summary.md (tests/stress/run.sh).
STRESS_RUNS ?= 5
stress-test: apt-deps
	tests/stress/run.sh $(STRESS_RUNS)

test: stages-begin lint test-core test-web test-browser test-api-fuzz test-examples fuzz-smoke test-rust
	$(STAGE)
	@awk 'NR > 1 { printf "  %-14s %5d s\n", name, $$2 - t; total += $$2 - t } { name = $$1; t = $$2 } \
	  END { printf "  %-14s %5d s\n", "total", total }' $(STAGES_LOG) | sed '1i make test: the stages (target/stages.log)'

stages-begin:
	@mkdir -p target && echo "install $$(date +%s)" > $(STAGES_LOG)

## bench: the criterion benches, then `isochron bench` (release) with its peers in
## the same run (filterpy's EKF and the Robotics Toolbox's C++ IK, in .venv-peers)
## and, when KUKA_CLIENT=path is given, KUKA's FRI client example beside isochron's.
PEER_VENV := .venv-peers
FILTERPY_VERSION := 2.0.0
RTB_VERSION := 1.5.0
KUKA_CLIENT ?=

peer-deps: $(PEER_VENV)/.peers-$(FILTERPY_VERSION)-$(RTB_VERSION)

$(PEER_VENV)/.peers-$(FILTERPY_VERSION)-$(RTB_VERSION):
	@[ -x $(PEER_VENV)/bin/python ] || $(PY) -m venv $(PEER_VENV)
	$(PEER_VENV)/bin/python -m pip install --quiet --disable-pip-version-check \
	  "filterpy==$(FILTERPY_VERSION)" "roboticstoolbox-python==$(RTB_VERSION)"
	@touch $@

bench: release peer-deps
	$(CARGO) bench --workspace
	"$${CARGO_TARGET_DIR:-target}/release/isochron" bench --peers $(PEER_VENV)/bin/python \
	  $(if $(KUKA_CLIENT),--kuka-client $(KUKA_CLIENT))

## types: the dashboard's TypeScript declarations from the Rust types (server/src/typescript.rs);
## `cargo test` fails while web/src/generated/types.ts is stale.
types:
	UPDATE_TS=1 $(CARGO) test -p server --lib typescript

## eval: the evaluation report beside the paper's results (reports/eval/report.md).
## The binary is where cargo put it (CARGO_TARGET_DIR, default ./target).
EVAL_N ?= 20
eval: release eval-world
	"$${CARGO_TARGET_DIR:-target}/release/isochron" eval --out reports/eval --n $(EVAL_N) --seed 1 --reality scenarios/reality.toml

## envelope: the reality lab's robustness envelope (issue #36): for every [world] factor of
## scenarios/reality.toml, then all together, the largest multiple of its range at which >= 95%
## of ENVELOPE_N trials succeed (bisection, the same seed per step); reports/envelope/envelope.md
## and envelope.svg. Not part of `make test`: 34 items of up to 6 steps of ENVELOPE_N trials in
## ENVELOPE_VISION (model: ~6 min on 2 cores; full: ~15 times that). ENVELOPE_SHARD=I/N runs the
## I-th of N slices of the factors (several processes or machines: the
## reports/envelope/envelope/shard-*.json files together, then
## `isochron eval --envelope --combine --out reports/envelope`).
ENVELOPE_N ?= 100
ENVELOPE_SHARD ?= 0/1
ENVELOPE_VISION ?= model
envelope: release
	"$${CARGO_TARGET_DIR:-target}/release/isochron" eval --envelope --reality scenarios/reality.toml \
	  --vision $(ENVELOPE_VISION) --out reports/envelope --n $(ENVELOPE_N) --seed 1 --shard $(ENVELOPE_SHARD)

## eval-world: the real lab end to end against `isochron world` (tests/tests/world/main.rs):
## EVAL_WORLD_N trials over REST on the truthful world (its pendulum, latency and robot steps
## first), then on the reality world (all five steps first), each paired with
## the world's truth; the figures (successes, the measured judge's agreement, |measured -
## true timing| p50/p95, CPU per second of service and world) go to reports/eval/world.txt.
## Then the accuracy of the real lab's five steps over EVAL_WORLD_DRAWS hidden
## draws of the reality world (a world and a lab each), against the truth each world printed:
## reports/eval/calibration-world.txt.
EVAL_WORLD_N ?= 100
EVAL_WORLD_DRAWS ?= 10
eval-world: deps firmware test-build
	@mkdir -p reports/eval
	WORLD_LAB_TRIALS=$(EVAL_WORLD_N) WORLD_LAB_STEPS=lab $(CARGO) test -p isochron-tests --test world trials_on -- --nocapture 2>&1 \
	  | grep -E "^(world lab|trial )" | tee reports/eval/world.txt
	WORLD_LAB_TRIALS=$(EVAL_WORLD_N) WORLD_LAB_SCENARIO=$(CURDIR)/scenarios/reality.toml WORLD_LAB_STEPS=all \
	  $(CARGO) test -p isochron-tests --test world trials_on -- --nocapture 2>&1 \
	  | grep -E "^(world lab|trial )" | tee -a reports/eval/world.txt
	WORLD_CALIB_DRAWS=$(EVAL_WORLD_DRAWS) WORLD_CALIB_LATENCY_MAX_MS=20 \
	  $(CARGO) test -p isochron-tests --test world the_calibration_steps_accuracy -- --nocapture 2>&1 \
	  | grep -E "^calibration accuracy" | tee reports/eval/calibration-world.txt
