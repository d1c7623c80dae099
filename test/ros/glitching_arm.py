"""Dynamixel servos whose joint readings glitch while a pose is measured, and a camera that
sees the true arm, for a session of the real arm_driver and sequencer; run as a subprocess in
the workspace environment.

    glitching_arm.py ROBOT_YAML IDS GLITCH_TICKS [OVERLOAD_POSE]

Prints the emulator's port (test/dynamixel_emulator.py: Protocol 2.0 servos IDS, e.g. 1,2,3,4,
on a pty) on its first line, then publishes /spots, 10 Hz: the robot's spots at the servos'
true positions, as Present Position reports them unglitched (q = (ticks - 2048) / (4096 / 2 pi), arm_driver's default mapping). Each time
the sequencer says a pose is 'measuring' (/session/progress: the arm has settled), the last
servo's next two reads of Present Position are GLITCH_TICKS off while it stays put, as a glitch
of its encoder or bus; the joint readings the driver publishes show it, the spots do not.
With OVERLOAD_POSE, the second servo overloads (Hardware Error Status 0x20, torque dropped) as the
arm moves to that pose (0-based step).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # test/: the emulator

from dynamixel_emulator import DynamixelEmulator  # noqa: E402
from laser_calib.model.kinematics import predict  # noqa: E402
from laser_calib.model.robot_file import load_robot  # noqa: E402
from laser_calib_interfaces.msg import SessionProgress, Spot, SpotPair  # noqa: E402
from spin_node import spin_until_interrupted  # noqa: E402

TICKS_PER_RAD = 4096 / (2 * math.pi)


def main() -> None:
    robot = load_robot(sys.argv[1])
    ids = [int(i) for i in sys.argv[2].split(",")]
    glitch_ticks = int(sys.argv[3])
    overload_pose = int(sys.argv[4]) if len(sys.argv) > 4 else None
    with DynamixelEmulator(ids=ids) as emulator:
        print(emulator.port, flush=True)
        rclpy.init()
        node = rclpy.create_node("glitching_arm")
        spots = node.create_publisher(SpotPair, "/spots", 10)
        glitched = set()  # the poses whose readings glitched

        def on_timer() -> None:
            q = np.array([(emulator.present_position(i) - 2048) / TICKS_PER_RAD for i in ids])
            p = predict(robot, q[None])
            pair = SpotPair(spots=[Spot(y=float(p.spots[0, j, 0]), z=float(p.spots[0, j, 1]), seen=bool(p.hit[0, j]))
                                   for j in range(2)])
            pair.header.stamp, pair.header.frame_id = node.get_clock().now().to_msg(), "screen"
            spots.publish(pair)

        def on_progress(msg: SessionProgress) -> None:
            if msg.state == "moving" and msg.done == overload_pose:
                emulator.set_hardware_error(ids[1], 0x20)
                print(f"overloaded servo {ids[1]}", flush=True)
            if msg.state == "measuring" and msg.pose not in glitched:
                glitched.add(msg.pose)
                emulator.glitch(ids[-1], 2, glitch_ticks)
                print(f"glitched pose {msg.pose}", flush=True)

        node.create_timer(0.1, on_timer)
        node.create_subscription(SessionProgress, "/session/progress", on_progress,
                                 QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        spin_until_interrupted(node)


if __name__ == "__main__":
    main()
