"""The main loop of the tests' own stand-in nodes (jtc_standin.py, glitching_arm.py), run as
scripts from this folder: spin until Ctrl-C, then destroy the node and shut rclpy down, so that
a stand-in exits 0 on Ctrl-C as the nodes it stands beside do."""

from __future__ import annotations

import rclpy
from rclpy.node import Node


def spin_until_interrupted(node: Node) -> None:
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
