# One-command set-up, run and test for cosserat_ros without a ROS install (PyPI wheels).
# Everything lands in $(VENV) (.venv); targets are idempotent (the install is redone only
# when a tracked input changes). Another interpreter gets a venv of its own, e.g.
# `make test-fast PYTHON=~/.pyenv/versions/3.12.1/bin/python3.12 VENV=.venv312`.
SHELL := /bin/bash
PYTHON ?= python3.11
VENV ?= .venv
PY := $(VENV)/bin/python
ENV := AMENT_PREFIX_PATH=$(abspath $(VENV)) ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
# what the node needs (requirements.txt): install and run; the stamp keeps its old name so
# that an existing venv is not reinstalled
DEPS_STAMP := $(VENV)/.deps-installed
# ... and the tools (requirements-dev.txt: pytest, ruff, sphinx, colcon, the extras the
# tests drive): test, test-fast, lint, docs
DEV_STAMP := $(VENV)/.dev-installed
PKG_STAMP := $(VENV)/.pkg-installed
BENCH_STAMP := $(VENV)/.bench-installed
PKG_SOURCES := $(shell find cosserat_ros config resource launch rviz -type f -not -path '*/__pycache__/*' 2>/dev/null) setup.py setup.cfg package.xml
PARAMS ?= config/cloth.yaml
# the fast tier: no test that starts a process, colcon, MuJoCo, a Ray cluster, or a long
# physics run (the markers are registered in pytest.ini; docs/testing.md)
FAST := not (process or colcon or bench or ray or slow)

.PHONY: install run view test test-fast docs lint validate bench clean

install: $(PKG_STAMP)

$(DEPS_STAMP): requirements.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade 'pip<25'
	$(PY) -m pip install --quiet -r requirements.txt
	touch $@

$(DEV_STAMP): $(DEPS_STAMP) requirements.txt requirements-dev.txt requirements-viz.txt \
		requirements-batch.txt requirements-bench.txt requirements-envs.txt \
		requirements-docs.txt
	$(PY) -m pip install --quiet -r requirements-dev.txt
	touch $@

# Installed exactly as colcon installs an ament_python package: python modules into
# site-packages, executables into $(VENV)/lib/cosserat_ros (where `ros2 run` looks), data
# files (package.xml, config, ament index marker) into $(VENV)/share.
# The build tree and the install's record are per venv (build/ for .venv): a second venv's
# install must not remove the first's files.
PKG_BUILD := $(if $(filter .venv,$(VENV)),build,build/$(subst /,_,$(VENV)))
$(PKG_STAMP): $(DEPS_STAMP) $(PKG_SOURCES)
	# the previous install's files first (a module moved or removed must not linger)
	if [ -f $(PKG_BUILD)/install-record.txt ]; then \
	    xargs -d '\n' rm -f < $(PKG_BUILD)/install-record.txt; fi
	rm -rf $(PKG_BUILD)/cosserat_ros_install && mkdir -p $(PKG_BUILD)
	$(PY) -W "ignore:setup.py install is deprecated" setup.py --quiet egg_info \
	    --egg-base $(PKG_BUILD) build --build-base $(PKG_BUILD)/cosserat_ros_install \
	    install --prefix $(abspath $(VENV)) --record $(PKG_BUILD)/install-record.txt \
	    --single-version-externally-managed >/dev/null
	touch $@

run: $(PKG_STAMP)
	$(ENV) $(VENV)/lib/cosserat_ros/cloth_node --ros-args --params-file $(PARAMS)

# the demo with the live view on: open ws://localhost:$(VIEW_PORT) in the Foxglove app
VIEW_PORT ?= 8765
VIZ_STAMP := $(VENV)/.viz-installed
$(VIZ_STAMP): $(DEPS_STAMP) requirements-viz.txt
	$(PY) -m pip install --quiet -r requirements-viz.txt
	touch $@

view: $(PKG_STAMP) $(VIZ_STAMP)
	$(ENV) $(VENV)/lib/cosserat_ros/cloth_node --ros-args --params-file $(PARAMS) \
	    -p foxglove.port:=$(VIEW_PORT)

# the whole suite (CI: .ci/run)
test: $(PKG_STAMP) $(DEV_STAMP) lint docs
	$(ENV) $(VENV)/bin/pytest -q --durations=20 test

# the fast tier, for the edit-test loop: a few minutes on 2 cores with a warm compile cache
test-fast: $(PKG_STAMP) $(DEV_STAMP) lint docs
	$(ENV) $(VENV)/bin/pytest -q --durations=10 -m '$(FAST)' test

# ruff over the whole tree (ruff.toml)
lint: $(DEV_STAMP)
	$(VENV)/bin/ruff check .

# the manual (doc/, the layout rosdoc2 builds) into build/doc, warnings as errors
docs: $(DEV_STAMP)
	$(ENV) $(PY) -m sphinx -W --keep-going -q -b html doc build/doc
	@echo "the manual: build/doc/index.html"

validate: $(PKG_STAMP)
	$(ENV) $(PY) -m cosserat_ros.tools.validate --out docs

# the bench's peer (MuJoCo) and the extras of its default batch and envs parts
$(BENCH_STAMP): $(DEPS_STAMP) requirements-bench.txt requirements-batch.txt requirements-envs.txt
	$(PY) -m pip install --quiet -r requirements-bench.txt -r requirements-batch.txt \
	    -r requirements-envs.txt
	touch $@

bench: $(PKG_STAMP) $(BENCH_STAMP)
	$(ENV) $(PY) -m cosserat_ros.tools.bench

clean:
	rm -rf $(VENV) build *.egg-info
