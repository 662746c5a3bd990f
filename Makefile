# Two-command set-up: `make demo` and `make test` each build what they need first.
# .venv -> every pinned package (.ci/constraints.txt: ROS 2 Jazzy wheels, the package's
# dependencies with the [train] extra: torch, onnx; a flight install, `pip install .`, has neither;
# README) -> art_guidance_msgs built into it, beside this package installed editable.
SHELL := /bin/bash
.SHELLFLAGS := -eo pipefail -c
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip --disable-pip-version-check -q
# The lock is installed as it is, without resolving (pip's resolver spent ~40 s of the set-up on
# it here): by uv, which installs in parallel (~13 s for all 230 packages here, against ~55 s for
# pip), from the sources pip is configured with (.ci/uv_sources.py); by pip where uv cannot be
# installed. `pip check` then proves the lock closed.
UV_VERSION := 0.13.9
UV := $(VENV)/bin/uv
CONSTRAINTS := .ci/constraints.txt
INSTALL = if [ -x $(UV) ]; then $(UV) pip install -q --python $(PY) \
		$$($(PY) .ci/uv_sources.py) $(1); \
	else $(PIP) install --no-compile $(1) 2>&1 | sed "/^WARNING: Location/d"; fi
# Nothing writes .pyc at install (pip would compile all ~15,000 modules of the dependencies, one
# at a time, ~40 s here); the steps that run the project (test, demo, bench, coverage) write
# them instead, for the ~2,300 modules a process really imports, at their first import (~6 s,
# once). They run with PYTHONDONTWRITEBYTECODE unset: where it is set, as on this project's
# machines, no process would write a .pyc and each of the suite's few hundred processes would
# compile torch, numpy and rclpy again at every import.
RUN := env -u PYTHONDONTWRITEBYTECODE
BUILD := build
MSG_SRC := $(wildcard msg_schemas/msg/*.msg) msg_schemas/CMakeLists.txt msg_schemas/package.xml
ROS_ENV := VIRTUAL_ENV=$(abspath $(VENV)) AMENT_PREFIX_PATH=$(abspath $(VENV)) \
	PATH=$(abspath $(VENV))/bin:$$PATH
PYTEST_ARGS ?=
# Test worker processes (pytest-xdist); 0 runs every test in this one process. A file whose
# fixtures outlive a test stays on one worker (test/conftest.py), hence --dist loadgroup.
TEST_JOBS ?= 2
# one BLAS and torch thread per process (unless OMP_NUM_THREADS is set): the workers share the cores
XDIST := $(if $(filter 0,$(TEST_JOBS)),,-n $(TEST_JOBS) --dist loadgroup)

.PHONY: all setup test test-fast coverage demo lint bench lock clean distclean

all: setup

$(VENV)/.stamp-venv:
	$(PYTHON) -m venv $(VENV)
	$(PIP) install --no-compile uv==$(UV_VERSION) 2>&1 | sed "/^WARNING: Location/d" \
		|| echo "uv could not be installed: pip installs the lock (slower)"
	touch $@

$(VENV)/.stamp-deps: $(VENV)/.stamp-venv $(CONSTRAINTS) .ci/uv_sources.py \
		.ci/fix_ros_cmake_paths.py
	$(call INSTALL,--no-deps -r $(CONSTRAINTS))
	$(PIP) check
	$(PY) .ci/fix_ros_cmake_paths.py
	$(RUN) $(PY) -c "import rclpy, rosidl_adapter, torch, onnx, onnxruntime, numba, clarabel, \
		osqp, cvxpy, rosbags, mcap_ros2" >/dev/null
	touch $@

$(VENV)/.stamp-msgs: $(VENV)/.stamp-deps $(MSG_SRC)
	rm -rf $(BUILD)/msgs && mkdir -p $(BUILD)
	$(ROS_ENV) cmake -S msg_schemas -B $(BUILD)/msgs -G Ninja -DBUILD_TESTING=OFF \
		-DCMAKE_INSTALL_PREFIX=$(abspath $(VENV)) -DPython3_EXECUTABLE=$(abspath $(PY)) \
		> $(BUILD)/msgs.log 2>&1 || (tail -40 $(BUILD)/msgs.log; exit 1)
	$(ROS_ENV) cmake --build $(BUILD)/msgs >> $(BUILD)/msgs.log 2>&1 \
		|| (tail -40 $(BUILD)/msgs.log; exit 1)
	$(ROS_ENV) cmake --install $(BUILD)/msgs >> $(BUILD)/msgs.log 2>&1 \
		|| (tail -40 $(BUILD)/msgs.log; exit 1)
	$(PY) -c "from art_guidance_msgs.msg import ManeuverPlan"
	touch $@

# this package (its dependencies are the lock's) needs the pinned packages, not the messages:
# the two build side by side (`setup`)
$(VENV)/.stamp-pkg: $(VENV)/.stamp-deps setup.py setup.cfg Makefile
	$(call INSTALL,--no-deps --no-build-isolation -e .)
	$(RUN) $(PY) -c "import art_guidance" >/dev/null
	touch $@

# the numba kernels compiled into their cache (a cold cache: ~20 s of one core), from the
# checkout, while the messages build: `make test` and `make demo` then find them there
$(VENV)/.stamp-kernels: $(VENV)/.stamp-deps $(wildcard art_guidance/kernels/*.py)
	mkdir -p $(BUILD)
	$(RUN) PYTHONPATH=$(CURDIR) $(PY) -m art_guidance.kernels > $(BUILD)/kernels.log 2>&1 \
		|| cat $(BUILD)/kernels.log
	touch $@

setup:
	@$(MAKE) --no-print-directory -j2 $(VENV)/.stamp-msgs $(VENV)/.stamp-pkg \
		$(VENV)/.stamp-kernels

# Before the tests, while flake8 runs: the kernels again (compiled at set-up; compiled again here
# only where their cache was cleared). The tests then load them (test/conftest.py warms them up
# again, which finds them in the cache).
test: setup
	mkdir -p $(BUILD)
	$(RUN) $(PY) -m art_guidance.kernels > $(BUILD)/kernels.log 2>&1 & kernels=$$!; \
	$(RUN) $(PY) -m flake8 art_guidance test benchmarks launch .ci setup.py || { wait $$kernels; exit 1; }; \
	wait $$kernels || cat $(BUILD)/kernels.log
	OMP_NUM_THREADS=$${OMP_NUM_THREADS:-1} $(RUN) $(PY) -m pytest -q $(XDIST) $(PYTEST_ARGS)

test-fast: setup
	OMP_NUM_THREADS=$${OMP_NUM_THREADS:-1} $(RUN) $(PY) -m pytest -q -m "not slow" $(XDIST) $(PYTEST_ARGS)

# The suite as `make test` runs it (pytest-xdist), under coverage: lines and branches of the whole
# package, in the pytest processes and in every Python process the tests start (setup.cfg
# [coverage:run] says how), then the per-package table of docs/reliability.md ("Coverage"). The
# table is written even when a test fails; the exit status is the suite's. `make test` runs
# without coverage.
COVERAGE_DIR := $(BUILD)/coverage
coverage: setup
	rm -rf $(COVERAGE_DIR) && mkdir -p $(COVERAGE_DIR)
	status=0; OMP_NUM_THREADS=$${OMP_NUM_THREADS:-1} $(RUN) $(PY) -m pytest -q $(XDIST) --cov \
		--cov-report= $(PYTEST_ARGS) || status=$$?; \
	$(PY) -m coverage json -q; \
	$(PY) .ci/coverage_table.py $(COVERAGE_DIR)/coverage.json docs/reliability.md; \
	exit $$status

lint: setup
	$(PY) -m flake8 art_guidance test benchmarks launch .ci setup.py

demo: setup
	$(RUN) $(VENV)/bin/art-guidance demo

bench: setup
	$(RUN) $(VENV)/bin/art-guidance bench all

# Re-resolve every dependency from the registries (newest allowed versions) and rewrite the pins.
lock:
	rm -rf $(BUILD)/lock-venv && mkdir -p $(BUILD)
	$(PYTHON) -m venv $(BUILD)/lock-venv
	$(BUILD)/lock-venv/bin/python -m pip --disable-pip-version-check -q install --dry-run \
		--ignore-installed --report $(BUILD)/lock.json \
		-r .ci/requirements-ros.txt ".[train,test,distributed]" 2>&1 \
		| sed "/^WARNING: Location/d"
	$(PYTHON) .ci/lock_pins.py $(BUILD)/lock.json $(CONSTRAINTS)
	rm -rf $(BUILD)/lock-venv
	@echo "pins rewritten: git diff $(CONSTRAINTS)"

clean:
	rm -rf $(BUILD) .pytest_cache out

distclean: clean
	rm -rf $(VENV) *.egg-info
