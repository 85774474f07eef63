# The two commands of the README: `make demo` and `make test`.
# Both create .venv in the repo and install everything from the package registries.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
ROS_PKGS := 'ros-jazzy-rclpy[fastrtps]' ros-jazzy-common-interfaces
# torch is pinned: 2.13.0 is the CPU build; any other spec downloads gigabytes.
TORCH := torch==2.13.0

.PHONY: venv test demo bench clean

venv: $(STAMP)

$(STAMP): setup.cfg setup.py package.xml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet $(ROS_PKGS) $(TORCH)
	$(PY) -m pip install --quiet -e '.[test,ros,torch]'
	touch $(STAMP)

test: $(STAMP)
	$(PY) -m pytest -q test

demo: $(STAMP)
	$(VENV)/bin/maem-demo

bench: $(STAMP)
	$(VENV)/bin/maem-bench

clean:
	rm -rf $(VENV) build *.egg-info
