"""A stand-in for robot_state_publisher (not on PyPI here), keeping its documented
contract for /robot_description: the URDF text as std_msgs/String, reliable,
transient local, depth 1, published once and kept for late subscribers.

    description_publisher.py URDF_FILE [TOPIC]     (runs until Ctrl-C)
"""

from __future__ import annotations

import sys
from pathlib import Path

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String


def main() -> int:
    text = Path(sys.argv[1]).read_text()
    topic = sys.argv[2] if len(sys.argv) > 2 else "robot_description"
    rclpy.init()
    node = rclpy.create_node("robot_state_publisher")
    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    node.create_publisher(String, topic, qos).publish(String(data=text))
    print(f"published {len(text)} characters on {topic}", flush=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
