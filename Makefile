# Two entry points on a fresh Debian 12 / Python 3.11 machine:
#   make demo   create .venv, install, run the main job on the simulated device
#   make test   create .venv if missing, install, run the whole test suite
PYTHON ?= python3
# pytest-xdist workers of make test (CI's machine has 2 cores; 1 runs the suite serially)
TEST_WORKERS ?= 2
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# The ROS wheels register their packages in an ament index inside the venv; nothing else
# points AMENT_PREFIX_PATH there, so every target that runs ROS code exports it.
export AMENT_PREFIX_PATH := $(abspath $(VENV))$(if $(AMENT_PREFIX_PATH),:$(AMENT_PREFIX_PATH))
export MPLBACKEND := Agg

.PHONY: demo test bench venv clean

venv: $(STAMP)

$(STAMP): requirements.txt setup.py $(wildcard mmd_ros/*/*.c)
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -r requirements.txt
	$(BIN)/python -m pip install --quiet --no-deps --no-build-isolation -e .
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m mmd_ros.demo

test: $(STAMP)
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadgroup test

bench: $(STAMP)
	$(BIN)/python bench/run_all.py

clean:
	rm -rf $(VENV) build install log out
