"""Arm backends (ROS-free): each provides ``joint_names``, ``command(q)``, ``read()``, ``stop()``, ``close()``.

Modules: dynamixel_arm (Dynamixel Protocol 2.0 servos through dynamixel_sdk; dynamixel_bus its packet exchange).
"""
