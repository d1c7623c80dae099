"""A full simulated calibration session (the node graph scripts/run-session runs).

    ros2 launch laser_calib_nodes session.launch.py output_dir:=/tmp/session [poses:=60] [robot:=...]
    ros2 launch laser_calib_nodes session.launch.py output_dir:=/tmp/session robot:=lasers.yaml \
        robot_description_topic:=/robot_description    # the arm's URDF from robot_state_publisher

Starts the simulated arm_driver, camera_sim, spot_detector, the estimator and
the sequencer (laser_calib_nodes.graph.session_nodes, shared with
scripts/run-session); `--show-args` lists the arguments. The launch takes the
session folder's lock first (a second session on a live folder is refused);
when the sequencer has finished (report written) or any node exits, the
launch shuts everything down.
"""

from laser_calib_nodes import graph


def generate_launch_description():
    return graph.launch_description(graph.SESSION_ARGS, graph.session_nodes)
