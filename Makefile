# cloe_ros: the two commands of the README work on a fresh machine (Python 3.10-3.13, x86_64):
#   make demo   set everything up, run the main job
#   make test   set everything up, run the test suite
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
	-not -name '*.pyc' 2>/dev/null) $(shell find bags -type f 2>/dev/null)
DEMO_ARGS ?=
TEST_ARGS ?=

# DDS stays on this machine; rcl logs go to the work tree, not ~/.ros.
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST
export ROS_LOG_DIR ?= $(CURDIR)/.ros_log
export AMENT_PREFIX_PATH := $(abspath $(VENV))
export MPLBACKEND := Agg

.PHONY: demo test install lint clean

demo: $(VENV)/.installed
	$(BIN)/cloe demo $(DEMO_ARGS)

test: $(VENV)/.installed
	$(BIN)/python -m pytest test $(TEST_ARGS)

install: $(VENV)/.installed

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(VENV)/.deps: requirements.txt | $(BIN)/python
	$(BIN)/pip install $(ROS_WHEELS) -r requirements.txt
	touch $@

$(VENV)/.installed: $(VENV)/.deps $(SOURCES)
	$(BIN)/pip install .
	touch $@

lint: $(VENV)/.installed
	$(BIN)/pip install ruff==0.17.6 >/dev/null
	$(BIN)/ruff check cloe_ros test

clean:
	rm -rf $(VENV) build *.egg-info .ros_log .pytest_cache
