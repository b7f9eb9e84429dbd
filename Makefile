# shocktwin — one Makefile; `make help` lists the targets.
# `make demo` and `make test` set everything up on a fresh machine first.

SHELL := /bin/bash
.SHELLFLAGS := -eu -o pipefail -c
.DEFAULT_GOAL := help

PY_SYS   ?= python3
VENV     := .venv
PY       := $(VENV)/bin/python
CARGO    ?= cargo
# Tests, binaries and the Python extension all use the release profile, so
# the dependencies are compiled once (2-core CI).
CARGO_PROFILE := --release
BIN      := target/release/shocktwin
OUT      ?= out
CAMPAIGN ?= $(OUT)/campaign
# The simulated damper's datasheet (rod, gas volume, oil volume, steel mass): calibration holds them.
DATASHEET ?= docs/datasheet.example.toml

RUST_SRC := $(shell find crates benches -name '*.rs' -o -name Cargo.toml 2>/dev/null) $(shell find crates/dt-server/assets -type f 2>/dev/null) Cargo.toml
PY_EXT_SRC := $(shell find crates/dt-core crates/dt-py crates/workspace-hack -name '*.rs' -o -name Cargo.toml -o -name '*.py' -o -name '*.pyi' -o -name pyproject.toml 2>/dev/null)

.PHONY: help setup build wheel browser demo test test-rust test-python lint fuzz bench bench-python load-test bench-nats study pgo clean

help: ## list the targets
	@grep -hE '^[a-zA-Z_-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-12s %s\n", $$1, $$2}'

$(VENV)/.deps: requirements.txt
	$(PY_SYS) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -r requirements.txt
	touch $@

$(VENV)/.shocktwin: $(VENV)/.deps $(PY_EXT_SRC)
	VIRTUAL_ENV=$(abspath $(VENV)) PATH=$(abspath $(VENV))/bin:$$PATH \
	  $(VENV)/bin/maturin develop -q --release -m crates/dt-py/Cargo.toml
	touch $@

# The CLI and the load generator only: `make demo` needs no test or bench target. The
# dependencies' features are unified across the workspace (crates/workspace-hack), so the
# bindings' build above, this one and `cargo test` below share one compilation of them.
$(BIN): $(RUST_SRC) Cargo.lock
	$(CARGO) build $(CARGO_PROFILE) -p dt-server --bins

setup: $(VENV)/.shocktwin $(BIN) ## create .venv, build the CLI and the Python package

wheel: $(VENV)/.deps ## build the abi3 wheel of the bindings into dist/ (maturin; manylinux tag of this machine's glibc)
	VIRTUAL_ENV=$(abspath $(VENV)) PATH=$(abspath $(VENV))/bin:$$PATH \
	  $(VENV)/bin/maturin build --release -m crates/dt-py/Cargo.toml --out dist

build: $(BIN) ## build the shocktwin CLI (release)

# Other units of the damper (unit seeds 400 on, apart from every unit a study scores), each run
# at two known charges at 2 Hz on the campaign's rig: the batch `observer unit-spread` measures the
# observer's unit-to-unit spread on (an end-of-line test of a few units at a gauged charge).
# $(1): the directory, $(2): how many units, $(3): more `simulate` flags.
SPREAD_CHARGES := 2 4 7 10 12
define other_units
rm -rf $(1); c=($(SPREAD_CHARGES)); for k in $$(seq 0 $$(($(2) - 1))); do \
  $(BIN) simulate $(3) --seed 1 --unit $$((400 + k)) --frequencies 2 \
    --pressures $${c[k % $${#c[@]}]},$${c[(k + 2) % $${#c[@]}]} --out $(1) > /dev/null; done
endef

# Other units again (unit seeds 500 on), each at the nominal 12 bar at 1 and 2 Hz on the campaign's
# rig: `observer transfer` measures on them how far a unit's error moves between excitations, which
# a baseline read at one and used at the other carries (dt-core ObserverParams::transfer_bar_per_ln_accel).
# Its `--unit` arguments: each unit's two runs. $(1): the directory, $(2): how many, $(3): more flags.
define transfer_units
rm -rf $(1); for k in $$(seq 0 $$(($(2) - 1))); do \
  $(BIN) simulate $(3) --seed 1 --unit $$((500 + k)) --frequencies 1,2 --pressures 12 \
    --out $(1)/u$$((500 + k)) > /dev/null; done
endef
transfer_args = $$(for d in $(1)/u*; do printf -- '--unit %s %s ' $$d/*.mcap; done)

demo: setup ## simulate the quick campaign, inspect, calibrate (physics, charge observer and its unit and transfer spreads on other units), read the charge on a road, study, a fleet's past and a leaking run through the daemon, dashboard screenshot (simulated data)
	@$(MAKE) --no-print-directory browser || echo "(without Chromium the demo skips the dashboard screenshot)"
	rm -rf $(OUT)
	$(BIN) simulate --quick --out $(CAMPAIGN)
	$(BIN) inspect $(CAMPAIGN)/p12.0-f2.0-s1.mcap
	$(PY) -m train.fit_physics --campaign $(CAMPAIGN) --out $(OUT)/physics.json --figures $(OUT)/figures --datasheet $(DATASHEET) --nominal-bar 12
	$(PY) -m train.observer fit --campaign $(CAMPAIGN) --physics $(OUT)/physics.json --datasheet $(DATASHEET)
	$(call other_units,$(OUT)/other-units,10,--quick)
	$(PY) -m train.observer unit-spread --physics $(OUT)/physics.json --campaign $(OUT)/other-units | tail -n 2
	$(call transfer_units,$(OUT)/transfer-units,10,--quick)
	$(PY) -m train.observer transfer --physics $(OUT)/physics.json --charge-bar 12 $(call transfer_args,$(OUT)/transfer-units) | tail -n 2
	$(BIN) simulate --quick --road 60 --out $(OUT)/road-cal
	$(BIN) simulate --quick --road 45 --seed 4 --out $(OUT)/road-cal45 && mv $(OUT)/road-cal45/*.mcap $(OUT)/road-cal/ && rmdir $(OUT)/road-cal45
	$(BIN) simulate --quick --road 60 --seed 2 --pressures 2,12 --out $(OUT)/road-held
	$(BIN) simulate --quick --road 60 --seed 3 --pressures 12 --out $(OUT)/road-baseline
	$(PY) -m train.road_observer fit --campaign $(OUT)/road-cal --physics $(OUT)/physics.json --out $(OUT)/road.json
	$(PY) -m train.road_observer evaluate --physics $(OUT)/physics.json --road $(OUT)/road.json --score-from-s 30 --out $(OUT)/road --baseline held=$(OUT)/road-baseline/p12.0-roadC60-s3.mcap@12 held=$(OUT)/road-held
	$(BIN) road --calibration $(OUT)/road.json --baseline $(OUT)/road-baseline/p12.0-roadC60-s3.mcap@12 --out $(OUT)/road/blocks.csv $(OUT)/road-held/*.mcap
	$(BIN) simulate --quick --road 5 --seed 2 --pressures 12 --out $(OUT)/road-slow
	$(BIN) road --calibration $(OUT)/road.json $(OUT)/road-slow/*.mcap
	$(PY) -W ignore -m train.study --quick --campaign $(CAMPAIGN) --physics $(OUT)/physics.json --datasheet $(DATASHEET) --out $(OUT)/study
	$(PY) -m train.demo_serve --bin $(BIN) --bundle $(OUT)/study/bundles/perm-18 --out $(OUT)/serve-demo --road $(OUT)/road.json --road-run $(OUT)/road-held/p2.0-roadC60-s2.mcap --road-baseline $(OUT)/road-baseline/p12.0-roadC60-s3.mcap@12
	@sed -n '/^## Table 2/,/^## Findings/{/^## Findings/!p}; /^## Targets/,/^Per run/{/^Per run/!p}; /^## Charge observer/,/^| set | run |/{/^| set | run |/!p}' $(OUT)/study/report.md
	@shot=$(OUT)/serve-demo/dashboard.png; [ -f $$shot ] || shot="not taken (no chromium)"; \
	echo "demo done (simulated data): report $(OUT)/study/report.md (with the plots), the charge read on a road $(OUT)/road/road_observer.md, figures $(OUT)/figures, dashboard $$shot (browse it again: $(BIN) serve --db $(OUT)/serve-demo/fleet.sqlite --model $(OUT)/study/bundles/perm-18 --config $(OUT)/serve-demo/road/serve.toml, then http://127.0.0.1:7411/)"

study: setup ## the full study on the default campaign: physics, charge observer (its unit and transfer spreads), Tables 2-3, suites (docs/study; simulated data)
	rm -rf $(OUT)/full-campaign
	$(BIN) simulate --out $(OUT)/full-campaign
	$(PY) -m train.fit_physics --campaign $(OUT)/full-campaign --out $(OUT)/full-physics.json --datasheet $(DATASHEET) --nominal-bar 12
	$(PY) -m train.observer fit --campaign $(OUT)/full-campaign --physics $(OUT)/full-physics.json --datasheet $(DATASHEET)
	$(call other_units,$(OUT)/full-other-units,20,)
	$(PY) -m train.observer unit-spread --physics $(OUT)/full-physics.json --campaign $(OUT)/full-other-units
	$(call transfer_units,$(OUT)/full-transfer-units,10,)
	$(PY) -m train.observer transfer --physics $(OUT)/full-physics.json --charge-bar 12 $(call transfer_args,$(OUT)/full-transfer-units) | tail -n 2
	$(PY) -W ignore -m train.study --campaign $(OUT)/full-campaign --physics $(OUT)/full-physics.json --datasheet $(DATASHEET) --out docs/study

# dt-bench holds no test, and its dev-dependency criterion would be compiled for nothing:
# `make bench` builds the benches, `make lint` checks them.
test-rust: ## Rust unit and integration tests
	$(CARGO) test $(CARGO_PROFILE) --workspace --exclude dt-py --exclude dt-bench

# The dashboard test drives Debian's Chromium through chromedriver (tests/python/test_dashboard.py).
# CI (CI=true, as root) installs them; elsewhere this says which command to run.
CHROMIUM_BIN     := /usr/bin/chromium
CHROMEDRIVER_BIN := /usr/bin/chromedriver
browser: ## check for (in CI as root: install) chromium and chromium-driver, for the dashboard test
	@if [ -x $(CHROMIUM_BIN) ] && [ -x $(CHROMEDRIVER_BIN) ]; then exit 0; fi; \
	if [ "$$(id -u)" = 0 ] && [ "$${CI:-}" = true ]; then \
	  apt-get update && apt-get install -y --no-install-recommends chromium chromium-driver; \
	else \
	  echo "chromium and chromedriver are needed for the dashboard test: sudo apt-get install chromium chromium-driver" >&2; \
	  exit 1; \
	fi

# Three workers on two cores: part of the tests' time waits on real-time streams and servers
# (the NATS failover, the daemon's drives), and a third worker fills it (docs/history.md, "Twenty-seventh session").
test-python: setup $(BIN) browser ## pytest: the Python contract, references and interop, the dashboard in Chromium
	$(PY) -m pytest -q -n 3 --dist loadfile --durations=15 tests/python

test: setup test-rust test-python ## set up, then run every test

lint: ## rustfmt and clippy (pedantic, workspace allow-list)
	$(CARGO) fmt --all -- --check
	$(CARGO) clippy $(CARGO_PROFILE) --workspace --all-targets -- -D warnings

# The fuzz harnesses of `cargo test` (dt-core: MCAP/JSON decoders; dt-server: config,
# import CSV/map/labels), run with a large budget: FUZZ_SECS per harness, 7 harnesses.
FUZZ_SECS ?= 85
fuzz: ## fuzz every decoder a remote party reaches, ~10 min (FUZZ_SECS per harness; SHOCKTWIN_FUZZ_SEED replays)
	mkdir -p $(OUT)
	$(CARGO) build $(CARGO_PROFILE) -p dt-core -p dt-server --tests
	SHOCKTWIN_FUZZ_CASES=1000000000 SHOCKTWIN_FUZZ_SECS=$(FUZZ_SECS) \
	  $(CARGO) test $(CARGO_PROFILE) -p dt-core -p dt-server --no-fail-fast --test it fuzz_ -- --nocapture --test-threads 1 2>&1 \
	  | tee $(OUT)/fuzz.log | grep -oE '(fuzz [a-z_/]+: [0-9]+ executions.*|^crash:.*|^minimal input.*|^test result.*)' || true
	@grep -ohE 'fuzz [a-z_/]+: [0-9]+ executions, [0-9]+ crashes' $(OUT)/fuzz.log | sort -u > $(OUT)/fuzz.summary
	@echo "executions: $$(awk '{s += $$3} END {print s}' $(OUT)/fuzz.summary), crashes: $$(awk '{s += $$5} END {print s}' $(OUT)/fuzz.summary) (log: $(OUT)/fuzz.log)"
	@! grep -q '^crash:' $(OUT)/fuzz.log

bench: ## criterion benches (see README for the figures)
	$(CARGO) bench -p dt-bench

bench-python: $(VENV)/.deps $(BIN) ## the Python reference (mcap, filterpy, scipy, onnxruntime) beside `shocktwin replay` on a 1 h log
	$(PY) benches/python_reference.py

# Profile-guided optimisation (the rustc book's recipe, with rustup's llvm-tools): an
# instrumented build replays a simulated quick campaign, then the profile guides a second build.
# Opt-in: two more compilations of everything (16–18 min on 2 cores); docs/perf.md has the figures.
PGO_DIR       := target/pgo
PGO_PROFDATA  = $(shell rustc --print sysroot)/lib/rustlib/$(shell rustc -vV | sed -n 's/^host: //p')/bin/llvm-profdata
pgo: $(BIN) ## opt-in: `shocktwin` built with profile-guided optimisation into target/pgo/release (16–18 min on 2 cores; see docs/perf.md)
	@command -v rustup >/dev/null || { echo "make pgo needs rustup (for its llvm-tools component)" >&2; exit 1; }
	rustup component add llvm-tools
	rm -rf $(PGO_DIR)/profiles $(PGO_DIR)/campaign && mkdir -p $(PGO_DIR)/profiles
	RUSTFLAGS="-Cprofile-generate=$(abspath $(PGO_DIR)/profiles)" \
	  $(CARGO) build --release --target-dir $(PGO_DIR)/instrumented -p dt-server --bin shocktwin
	@# What the build scripts wrote is not the workload.
	rm -rf $(PGO_DIR)/profiles && mkdir -p $(PGO_DIR)/profiles
	$(PGO_DIR)/instrumented/release/shocktwin simulate --quick --out $(PGO_DIR)/campaign >/dev/null
	$(PGO_DIR)/instrumented/release/shocktwin replay --model crates/dt-core/tests/fixtures/bundle-mlp13 \
	  $(PGO_DIR)/campaign/*.mcap --out $(PGO_DIR)/campaign/estimates.csv | tail -n 1
	@# The daemon's path too: 100 simulated assets streaming 30 s over loopback into the
	@# instrumented `serve` (the default build's load generator; stopped with SIGTERM, so the
	@# daemon exits normally and writes its profile). Exit 1 only says the count did not hold
	@# its delay on a busy machine: the profile is written all the same; 2 is an error.
	target/release/shocktwin-load --serve $(PGO_DIR)/instrumented/release/shocktwin \
	  --model crates/dt-core/tests/fixtures/bundle-mlp13 --assets 100 --duration-s 30 \
	  || [ $$? -eq 1 ]
	"$(PGO_PROFDATA)" merge -o $(PGO_DIR)/merged.profdata $(PGO_DIR)/profiles
	RUSTFLAGS="-Cprofile-use=$(abspath $(PGO_DIR)/merged.profdata)" \
	  $(CARGO) build --release --target-dir $(PGO_DIR) -p dt-server --bin shocktwin
	@echo "built $(PGO_DIR)/release/shocktwin (profile-guided; the default build is $(BIN))"

LOAD_ASSETS ?= 100,200,300,400,500
bench-nats: $(VENV)/.deps $(BIN) ## throughput of the NATS worker group, 1 vs 2 workers, on a real nats-server (a bench, minutes; simulated data)
	$(PY) benches/nats_scale.py

load-test: $(BIN) ## load test of shocktwin serve over loopback (a bench, minutes; exits 1 if a count breaks), see docs/daemon.md
	mkdir -p $(OUT)
	target/release/shocktwin-load --serve $(BIN) --model crates/dt-core/tests/fixtures/bundle-mlp13 --assets $(LOAD_ASSETS) --duration-s 60 --json-out $(OUT)/load-test.jsonl

clean: ## remove build outputs, the venv, dist/ and out/
	rm -rf target $(VENV) $(OUT) dist
