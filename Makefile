# The two commands of the README: `make demo` and `make test`.
# Both create .venv in the repo and install everything from the package registries.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# tf2_msgs built from its upstream definition (no PyPI wheel); ros_msgs/build.sh never fails
# the build: without a compiler it says so in one line and the nodes skip TF
TF2_STAMP := $(VENV)/.tf2_msgs
TF2_SOURCES := ros_msgs/build.sh ros_msgs/cmake/fix_wheel_include_dirs.cmake \
	ros_msgs/tf2_msgs/CMakeLists.txt ros_msgs/tf2_msgs/package.xml ros_msgs/tf2_msgs/msg/TFMessage.msg
ROS_PKGS := 'ros-jazzy-rclpy[fastrtps]' ros-jazzy-common-interfaces
# torch is pinned: 2.13.0 is the CPU build; any other spec downloads gigabytes.
TORCH := torch==2.13.0

.PHONY: venv test demo bench clean

venv: $(STAMP) $(TF2_STAMP)

$(STAMP): setup.cfg setup.py package.xml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet $(ROS_PKGS) $(TORCH)
	$(PY) -m pip install --quiet -e '.[test,ros,torch]'
	touch $(STAMP)

$(TF2_STAMP): $(STAMP) $(TF2_SOURCES)
	bash ros_msgs/build.sh $(VENV)
	touch $(TF2_STAMP)

test: $(STAMP) $(TF2_STAMP)
	$(PY) -m pytest -q test

demo: $(STAMP) $(TF2_STAMP)
	$(VENV)/bin/maem-demo

bench: $(STAMP)
	$(VENV)/bin/maem-bench

clean:
	rm -rf $(VENV) build *.egg-info
