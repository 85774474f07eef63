# The two commands of the README: `make demo` and `make test`.
# `make test-fast`: the unit and core tests only (no ROS, colcon, download or slow test);
# `make lint`: ruff and mypy on maem_ros/ (make test runs it first).
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

MEDIAPIPE := mediapipe==0.10.21
MP_STAMP := $(VENV)/.mediapipe
# numba kernels compiled into their on-disk cache (maem_ros/**/__pycache__) as part of the
# install, so the first demo / node start loads them instead of compiling; redone when a core
# source changes (maem-warmup recompiles only kernels whose imports changed)
KERNELS_STAMP := $(VENV)/.kernels
CORE_SOURCES := $(shell find maem_ros/core -name '*.py')

.PHONY: venv test test-fast lint demo bench clean mediapipe pose2sim-demo

venv: $(STAMP) $(TF2_STAMP) $(KERNELS_STAMP)

# The optional mediapipe frontend: its runtime deps as the [mediapipe] extra, the wheel (models
# included) with --no-deps, as its own requirements pin numpy<2 and opencv-contrib-python. `make
# test` tries it too; when the wheel cannot be had, the mediapipe tests skip with the reason.
mediapipe: $(STAMP)
	$(PY) -m pip install --quiet -e '.[mediapipe]'
	$(PY) -m pip install --quiet --no-deps $(MEDIAPIPE)
	touch $(MP_STAMP)

$(MP_STAMP): $(STAMP)
	-$(MAKE) --no-print-directory mediapipe || echo "make: $(MEDIAPIPE) not installed; its tests will skip"
	touch $(MP_STAMP)

$(STAMP): setup.cfg setup.py package.xml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet $(ROS_PKGS) $(TORCH)
	$(PY) -m pip install --quiet -e '.[test,ros,torch]'
	touch $(STAMP)

$(TF2_STAMP): $(STAMP) $(TF2_SOURCES)
	bash ros_msgs/build.sh $(VENV)
	touch $(TF2_STAMP)

$(KERNELS_STAMP): $(STAMP) $(CORE_SOURCES) maem_ros/tools/warmup.py
	$(VENV)/bin/maem-warmup --quiet
	touch $(KERNELS_STAMP)

# the test markers (setup.cfg [tool:pytest]) that make test-fast leaves out
SLOW_KINDS := not ros and not slow and not colcon and not network

lint: $(STAMP)
	$(VENV)/bin/ruff check maem_ros
	$(VENV)/bin/ruff format --check maem_ros
	$(VENV)/bin/mypy

test: lint $(TF2_STAMP) $(MP_STAMP) $(KERNELS_STAMP)
	$(PY) -m pytest -q test

# two workers (pytest-xdist): the unit tests are independent and CPU-bound; make test stays
# serial, its graph tests each own a DDS participant and wait on timeouts
test-fast: $(STAMP) $(KERNELS_STAMP)
	$(PY) -m pytest -q -n 2 test -m "$(SLOW_KINDS)"

demo: $(STAMP) $(TF2_STAMP) $(KERNELS_STAMP)
	$(VENV)/bin/maem-demo

pose2sim-demo: mediapipe
	$(VENV)/bin/maem-pose2sim-demo

bench: $(STAMP) $(KERNELS_STAMP)
	$(VENV)/bin/maem-bench

clean:
	rm -rf $(VENV) build *.egg-info
