# One-command set-up, run and test for cosserat_ros without a ROS install (PyPI wheels).
# Everything lands in .venv; targets are idempotent (the install is redone only when a
# tracked input changes).
SHELL := /bin/bash
PYTHON ?= python3.11
VENV := .venv
PY := $(VENV)/bin/python
ENV := AMENT_PREFIX_PATH=$(CURDIR)/$(VENV) ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
DEPS_STAMP := $(VENV)/.deps-installed
PKG_STAMP := $(VENV)/.pkg-installed
BENCH_STAMP := $(VENV)/.bench-installed
PKG_SOURCES := $(shell find cosserat_ros config resource launch rviz -type f -not -path '*/__pycache__/*' 2>/dev/null) setup.py setup.cfg package.xml
PARAMS ?= config/cloth.yaml

.PHONY: install run view test docs lint validate bench clean

install: $(PKG_STAMP)

$(DEPS_STAMP): requirements.txt requirements-dev.txt requirements-viz.txt requirements-batch.txt \
		requirements-envs.txt requirements-docs.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade 'pip<25'
	$(PY) -m pip install --quiet -r requirements-dev.txt
	touch $@

# Installed exactly as colcon installs an ament_python package: python modules into
# site-packages, executables into $(VENV)/lib/cosserat_ros (where `ros2 run` looks), data
# files (package.xml, config, ament index marker) into $(VENV)/share.
$(PKG_STAMP): $(DEPS_STAMP) $(PKG_SOURCES)
	# the previous install's files first (a module moved or removed must not linger)
	if [ -f build/install-record.txt ]; then xargs -d '\n' rm -f < build/install-record.txt; fi
	rm -rf build/cosserat_ros_install && mkdir -p build
	$(PY) -W "ignore:setup.py install is deprecated" setup.py --quiet egg_info --egg-base build \
	    build --build-base build/cosserat_ros_install \
	    install --prefix $(CURDIR)/$(VENV) --record build/install-record.txt \
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

test: $(PKG_STAMP) lint docs
	$(ENV) $(VENV)/bin/pytest -q --durations=20 test

# ruff over the whole tree (ruff.toml)
lint: $(DEPS_STAMP)
	$(VENV)/bin/ruff check .

# the manual (doc/, the layout rosdoc2 builds) into build/doc, warnings as errors
docs: $(DEPS_STAMP)
	$(ENV) $(PY) -m sphinx -W --keep-going -q -b html doc build/doc
	@echo "the manual: build/doc/index.html"

validate: $(PKG_STAMP)
	$(ENV) $(PY) -m cosserat_ros.tools.validate --out docs

$(BENCH_STAMP): $(DEPS_STAMP) requirements-bench.txt
	$(PY) -m pip install --quiet -r requirements-bench.txt
	touch $@

bench: $(PKG_STAMP) $(BENCH_STAMP)
	$(ENV) $(PY) -m cosserat_ros.tools.bench

clean:
	rm -rf $(VENV) build *.egg-info
