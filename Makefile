# One entry for set-up, demo and tests on a fresh Debian machine (Python >= 3.11).
# `make demo` and `make test` create .venv and install everything they need (the service, the
# simulator, the evaluation, the development tools and Ray for the cluster test:
# `.[dev,eval,sim,cluster]`).
# A board: `sudo make install` (the service alone, under systemd; docs/install.md).
PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed
OUT     ?= out

.PHONY: all venv sysdeps demo demo-px4 test lint typecheck unit bench results results-attitude results-real \
	results-dpose dist install uninstall check-arm64 clean

all: test

# System packages: only what the Python wheels do not bring (venv support on Debian's python3,
# the Mosquitto broker that the MQTT tests start on 127.0.0.1, GStreamer with its Python
# bindings for `gst:` cameras: the pip OpenCV has no GStreamer; docs/decisions.md, "Cameras";
# and Chromium, the headless browser that opens the live page in tests/e2e/test_web_browser.py).
GST_DEBS := python3-gi gir1.2-gstreamer-1.0 gir1.2-gst-plugins-base-1.0 \
	gstreamer1.0-plugins-base gstreamer1.0-plugins-good
sysdeps:
	@missing=$$(for p in $(GST_DEBS); do dpkg-query -W -f='$${Status}' $$p 2>/dev/null \
	  | grep -q 'ok installed' || echo $$p; done); \
	if [ -n "$$missing" ] && command -v apt-get >/dev/null; then \
	  echo "installing $$missing (apt-get)"; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing; fi
	@$(PY) -c 'import ensurepip, venv' 2>/dev/null || { \
	  echo "installing python3-venv (apt-get)"; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq python3-venv; }
	@command -v mosquitto >/dev/null 2>&1 || test -x /usr/sbin/mosquitto || { \
	  echo "installing mosquitto (apt-get)"; \
	  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq mosquitto >/dev/null 2>&1 || { \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq mosquitto; }; }
	@command -v chromium >/dev/null 2>&1 || { \
	  echo "installing chromium (apt-get)"; \
	  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null 2>&1 || { \
	    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium; } || \
	    echo "chromium not installed: tests/e2e/test_web_browser.py skips, saying why"; }; }

$(STAMP): pyproject.toml | sysdeps
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev,eval,sim,cluster]'
	touch $(STAMP)

# Debian's gi (GStreamer's bindings) made importable in the venv, nothing else of the system's
# packages (systemd/venv-system-modules.sh; skipped with a message if built for another Python)
$(VENV)/system-modules/gi: | $(STAMP)
	bash systemd/venv-system-modules.sh $(VENV) gi

venv: $(STAMP) $(VENV)/system-modules/gi

# The SITL autopilot and the service together on the default scenario (hills, lawnmower, 60 s,
# real time over loopback); prints what the autopilot received and where the plots are. The
# camera is rendered first (about a minute), so that on a 2-core machine the renderer does not
# take the CPU from the service during the flight (docs/BENCHMARKS.md has both figures).
demo: venv
	$(BIN)/companion demo --config config/sitl.toml --prerender --out $(OUT)/demo

# the real PX4 (SIH) flies a 20 m square on our estimate, GPS off (docs/RESULTS.md, "PX4 in the
# loop"); MISSION=lawnmower|hover, SEED=N; needs ../shared/px4-sitl or PX4_SITL (docs/install.md)
demo-px4: venv
	$(BIN)/companion sitl px4 --mission $(or $(MISSION),square) --seed $(or $(SEED),1) --out $(OUT)/px4-$(or $(MISSION),square)

lint: venv
	$(BIN)/ruff check companion drivers sitl tests systemd
	$(BIN)/ruff format --check companion drivers sitl tests systemd
	$(BIN)/lint-imports --no-cache   # the one-way layers (pyproject.toml [tool.importlinter])

typecheck: venv
	$(BIN)/mypy

# Two pytest-xdist workers by default (PYTEST_WORKERS=0: serial). tests/conftest.py and
# tests/peers/__init__.py keep the real autopilots on one worker and give every real-time flight the
# machine to itself (its camera prerendered beside the other worker's tests), so the second
# core runs the CPU-bound tests while no flight is on: 14:55 against 20:38 serial on this
# 2-core machine (docs/BENCHMARKS.md, "Later on 2026-11-25 (8eac457)"; docs/decisions.md,
# "Two test workers").
PYTEST_WORKERS ?= 2
unit: venv sysdeps
	$(BIN)/python -m pytest $(if $(filter-out 0,$(PYTEST_WORKERS)),-n $(PYTEST_WORKERS) --dist loadgroup)

test: lint typecheck unit

bench: venv
	$(BIN)/companion bench render
	$(BIN)/companion bench vo --terrain hills --trajectory lawnmower --seconds 60
	$(BIN)/companion bench attitude --terrain hills --trajectory lawnmower --seconds 60
	$(BIN)/companion bench dpose --terrain hills --seconds 30

# docs/RESULTS.md, metric scale: every method on 4 terrains x 2 trajectories x 3 seeds (long)
RESULTS := $(OUT)/results
results: venv
	@mkdir -p $(RESULTS)
	for t in hills urban flat slope; do for tr in lawnmower figure8; do for s in 1 2 3; do \
	  $(BIN)/companion eval --methods all --terrain $$t --trajectory $$tr --seconds 60 \
	    --seed $$s --out $(RESULTS)/$$t-$$tr-$$s --no-progress || exit 1; done; done; done
	$(BIN)/companion eval --methods all --sensor-study --terrain hills --trajectory lawnmower \
	  --seconds 60 --seed 1 --out $(RESULTS)/study-hills --no-progress
	$(BIN)/companion report $(RESULTS)/*-*-*

# docs/RESULTS.md, real sequences: rebuilt from their public git snapshots
# (config/real_sequences.toml; SNAPSHOTS holds owner+name/repo bare clones), every method on each
SNAPSHOTS ?= ../.mirror
results-real: venv
	@mkdir -p $(RESULTS)/real
	$(BIN)/companion dataset rebuild --all --snapshots $(SNAPSHOTS) --out $(RESULTS)/real/data
	for d in $(RESULTS)/real/data/*; do \
	  $(BIN)/companion eval $$d --methods all --no-progress \
	    --out $(RESULTS)/real/$$(basename $$d) || exit 1; done
	$(BIN)/companion report $(RESULTS)/real/tum_* $(RESULTS)/real/rislab_*

# docs/RESULTS.md, roll/pitch (issue 5) and d-Pose (issue 6)
results-attitude: venv
	for t in flat hills urban slope; do \
	  $(BIN)/companion eval --attitude --terrain $$t --seconds 60 --spacing 0.5 --no-progress \
	    --out $(RESULTS)/attitude-$$t || exit 1; done
	$(BIN)/companion eval --attitude --terrain flat --seconds 60 --spacing 0.5 --study \
	  --no-progress --out $(RESULTS)/attitude-study
	$(BIN)/companion eval --attitude --terrain hills --trajectory circle --seconds 600 \
	  --spacing 0.5 --no-progress --out $(RESULTS)/attitude-hills-circle-600

results-dpose: venv
	for t in flat hills slope; do \
	  $(BIN)/companion eval --dpose --terrain $$t --seconds 60 --out $(RESULTS)/dpose-$$t \
	  || exit 1; done
	$(BIN)/companion eval --dpose --random 10000

# the wheel (companion, drivers, sitl; runtime dependencies, extras sim/eval/dev) and the sdist
# (also the Makefile, configs, unit, docs and tests) in dist/
dist: venv
	$(BIN)/python -m build --outdir dist

# A board, as root: the service user, a runtime-only venv in /opt/companion/venv, the unit,
# /etc/companion/config.toml (never overwritten) and /var/lib/companion; `uninstall` removes
# all but the config and the state. PY=python3.11 for another interpreter, WHEEL=FILE to
# install a built wheel, PREFIX / SYSCONFDIR to move it (systemd/board-install.sh).
install:
	PY='$(PY)' bash systemd/board-install.sh install

uninstall:
	bash systemd/board-install.sh uninstall

# The board's install and a recorded replay on arm64 Debian 12, emulated here (qemu-user-static
# and proot over a debootstrap root in ARM64_ROOT, default /var/tmp/companion-arm64, reused):
# `pip install` and `make install` from wheels, the first start, and `companion eval` of the
# TUM clip compared pose by pose with x86's (systemd/check-arm64.sh; docs/install.md,
# "arm64"). As root; minutes, so not in `make test`. HOST_PY: the x86 Python to compare with.
check-arm64:
	HOST_PY='$(or $(HOST_PY),$(abspath $(BIN)/python))' bash systemd/check-arm64.sh

clean:
	rm -rf $(VENV) $(OUT) dist .mypy_cache .ruff_cache .pytest_cache
