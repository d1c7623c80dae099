# Source this file (bash) to use the workspace built by scripts/setup:
#   source scripts/env.sh
# It activates .venv (ROS 2 Jazzy from PyPI wheels) and the colcon install of
# ros2_ws, so the node executables in ros2_ws/install/laser_calib_nodes/lib/
# laser_calib_nodes/, `laser-calib` and `python -c "import rclpy, laser_calib_interfaces"` work,
# and `ros2` when the ROS 2 command line is installed in .venv (.ci/run does it).
# Without .venv but on a ROS install (/opt/ros/<distro>, e.g. docker/Dockerfile),
# it sources that ROS instead.
# Traffic stays on this host unless ROS_AUTOMATIC_DISCOVERY_RANGE is already set.
_lc_root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
if [ ! -f "$_lc_root/ros2_ws/install/setup.bash" ]; then
  echo "env.sh: workspace not built; run scripts/setup first" >&2
  return 1 2>/dev/null || exit 1
fi
_lc_nounset=$([[ $- == *u* ]] && echo 1 || true)
set +u
if [ -x "$_lc_root/.venv/bin/python" ]; then
  # shellcheck disable=SC1091
  source "$_lc_root/.venv/bin/activate"
elif [ -f "/opt/ros/${ROS_DISTRO:-jazzy}/setup.bash" ]; then
  # shellcheck disable=SC1090
  source "/opt/ros/${ROS_DISTRO:-jazzy}/setup.bash"
fi
# shellcheck disable=SC1091
source "$_lc_root/ros2_ws/install/setup.bash"
if [ -x "$_lc_root/.venv/bin/python" ]; then
  # The wheels' packages (std_msgs, rcl_interfaces, ...) are installed in the venv's prefix:
  # without it on AMENT_PREFIX_PATH, ament_index (ros2 interface, launch) does not find them.
  case ":$AMENT_PREFIX_PATH:" in
    *":$_lc_root/.venv:"*) ;;
    *) export AMENT_PREFIX_PATH="$AMENT_PREFIX_PATH:$_lc_root/.venv" ;;
  esac
  # The real ros2 command line, when installed (../shared/tools/ros2cli/install.sh .venv).
  # shellcheck disable=SC1091
  if [ -f "$_lc_root/.venv/opt/ros2cli/env.sh" ]; then source "$_lc_root/.venv/opt/ros2cli/env.sh"; fi
fi
# The command line as the docs write it, `laser-calib` (colcon installs the entry point where
# `ros2 run laser_calib laser-calib` finds it, not on PATH).
case ":$PATH:" in
  *":$_lc_root/ros2_ws/install/laser_calib/lib/laser_calib:"*) ;;
  *) export PATH="$_lc_root/ros2_ws/install/laser_calib/lib/laser_calib:$PATH" ;;
esac
[ -n "$_lc_nounset" ] && set -u
export ROS_AUTOMATIC_DISCOVERY_RANGE=${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}
# Fast DDS's profile for 4 MB camera frames (config/fastdds_large_frames.xml: why), for every
# process started from this shell, a camera driver of your own included, unless one is set.
if [ -z "${FASTRTPS_DEFAULT_PROFILES_FILE:-}" ] && [ "${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}" = rmw_fastrtps_cpp ]; then
  export FASTRTPS_DEFAULT_PROFILES_FILE="$_lc_root/config/fastdds_large_frames.xml"
fi
export LASER_CALIB_NODES="$_lc_root/ros2_ws/install/laser_calib_nodes/lib/laser_calib_nodes"
unset _lc_root _lc_nounset
