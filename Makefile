# cloe_ros: the two commands of the README work on a fresh machine (Python 3.10-3.13, x86_64):
#   make demo   set everything up, run the main job
#   make test   set everything up, run the test suite (TEST_WORKERS processes in parallel)
#   make test-under-load   the same, while busy loops occupy every core
# Both create ./.venv, install the ROS 2 Jazzy wheels and the pinned requirements into it, then
# install this package with a regular (non-editable) install so its data files and ament index
# marker exist, as `ros2 run` on a ROS machine expects.

PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
ROS_WHEELS := 'ros-jazzy-rclpy[fastrtps]' ros-jazzy-nav-msgs ros-jazzy-geometry-msgs \
	ros-jazzy-std-msgs ros-jazzy-std-srvs ros-jazzy-diagnostic-msgs ros-jazzy-rosgraph-msgs \
	ros-jazzy-visualization-msgs
SOURCES := setup.py setup.cfg package.xml $(shell find cloe_ros config resource launch viewers -type f \
	-not -name '*.pyc' -not -name '_kernels_ahead_*' 2>/dev/null) $(shell find bags -type f 2>/dev/null)
DEMO_ARGS ?=
TEST_ARGS ?=
# parallel test processes (pytest-xdist); each reserves a DDS domain of its own (test/conftest.py)
TEST_WORKERS ?= auto
# (no path given: pytest.ini's testpaths, test/; TEST_ARGS=test/ros runs that folder alone)
PYTEST := $(BIN)/python -m pytest -n $(TEST_WORKERS) --dist worksteal

# DDS stays on this machine; rcl logs go to the work tree, not ~/.ros.
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST
export ROS_LOG_DIR ?= $(CURDIR)/.ros_log
export AMENT_PREFIX_PATH := $(abspath $(VENV))
export MPLBACKEND := Agg

.PHONY: demo test test-under-load install lint clean

demo: $(VENV)/.installed
	$(BIN)/cloe demo $(DEMO_ARGS)

test: $(VENV)/.installed
	$(PYTEST) $(TEST_ARGS)

# one busy loop per core for as long as the suite runs, stopped whatever its outcome
test-under-load: $(VENV)/.installed
	$(BIN)/python scripts/under_load.py -- $(PYTEST) $(TEST_ARGS)

install: $(VENV)/.installed

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(VENV)/.deps: requirements.txt | $(BIN)/python
	$(BIN)/pip install $(ROS_WHEELS) -r requirements.txt
	touch $@

# (then the compiled kernels, cloe_ros/core/kernels.py, are built ahead into one extension module,
# cloe_ros/core/ahead.py, for the installed package and for the work tree the tests import, which
# also fills numba's cache: no node or test process started later waits on a compile, and none
# imports numba. Where the build cannot be made (no C compiler), numba's cache alone serves.)
KERNEL_IMPORTS := 'import cloe_ros.core.kernels, cloe_ros.core.kernels_covariance, cloe_ros.core.identifier, cloe_ros.core.anticipation'
$(VENV)/.installed: $(VENV)/.deps $(SOURCES)
	$(BIN)/pip install .
	cd / && ($(abspath $(BIN))/python -m cloe_ros.core.ahead \
		|| CLOE_ROS_KERNELS=jit $(abspath $(BIN))/python -c $(KERNEL_IMPORTS))
	$(BIN)/python -m cloe_ros.core.ahead || CLOE_ROS_KERNELS=jit $(BIN)/python -c $(KERNEL_IMPORTS)
	touch $@

lint: $(VENV)/.installed
	$(BIN)/pip install ruff==0.17.6 >/dev/null
	$(BIN)/ruff check cloe_ros test scripts

clean:
	rm -rf $(VENV) build *.egg-info .ros_log .pytest_cache
