#!/usr/bin/env bash
# Container entry point: a full simulated session into /out/session, then
# `ros2 bag info` on its bag (rosbag2 reading what rosbags wrote).
# Arguments are passed to scripts/run-session (e.g. --poses 20 --span small).
set -eo pipefail
# shellcheck disable=SC1091
source /opt/ros/jazzy/setup.bash
cd /opt/laser_calib
scripts/run-session --no-setup --out /out/session "$@"
ros2 bag info /out/session/bag
