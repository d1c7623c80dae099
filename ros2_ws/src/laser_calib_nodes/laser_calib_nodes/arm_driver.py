"""arm_driver: joint goals in, joint states out, over a simulated or a Dynamixel arm.

Subscribes  joint_trajectory (trajectory_msgs/JointTrajectory), accepted under the
            rules of ros2_control's joint_trajectory_controller
            (laser_calib.hardware.trajectory: every joint named, in any order;
            time_from_start strictly increasing; sizes matching) and refused,
            with one log line, otherwise or when the goal leaves the joint
            limits; the arm keeps its goal. The positions of the LAST point are
            the goal; the arm moves there on its own profile (intermediate
            points and timing are not followed: a calibration needs only the
            still poses).
Publishes   joint_states (sensor_msgs/JointState) at ``rate`` Hz: position
            (rad) and velocity (rad/s) as read from the arm.
            sim/true_spots (laser_calib_interfaces/TrueSpots), backend 'sim' only:
            the true spots of the two lasers (true robot at the true joint
            angles, laser_calib.model.kinematics.predict), stamped like the joint
            state of the same instant. Private to the simulation: camera_sim
            renders them; nothing else may use them.
            /diagnostics (diagnostic_msgs/DiagnosticArray): the status '<node>: arm',
            OK once a second, ERROR with the cause when a fault stops the arm
            (arm_status.py).
"""

from __future__ import annotations

import math
import sys

import numpy as np
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

from laser_calib.io.errors import InputError
from laser_calib.model.robot_file import dump_robot, load_robot, save_robot
from laser_calib.sim.simulation import NoiseSpec, true_errors

from laser_calib_nodes import common, parameters
from laser_calib_nodes.arm_status import ArmStatus
from laser_calib.hardware.backends import SimArm, dynamixel_backend
from laser_calib.hardware.trajectory import TrajectoryPoint, trajectory_goal
from laser_calib.io.joint_names import RobotJoints

TORQUE_NOT_CONFIRMED = 5  # exit code: a servo did not confirm torque off on shutdown


class ArmDriver(Node):
    def __init__(self):
        super().__init__("arm_driver")
        declare = lambda *a, **k: parameters.declare(self, *a, **k)  # noqa: E731
        backend = declare("backend", "sim", "Arm backend: 'sim' (simulated true robot) or 'dynamixel'.")
        self.robot, robot_path = common.robot_param(self, lasers=backend == "sim")  # sim: it publishes the true spots
        n = self.robot.n_joints
        names = declare("joint_names", Parameter.Type.STRING_ARRAY,
                        "Joint names, base to tip (default joint1..jointN; a URDF arm's: its joints').",
                        type_=Parameter.Type.STRING_ARRAY)
        self.joint_names = RobotJoints(self.robot, names, "parameter joint_names").names  # checked: one per joint
        rate = declare("rate", 50.0, "Joint state publishing rate, Hz.", rule=parameters.rate)

        # simulation
        true_path = declare("sim.true_robot", "", "Sim: true robot model file; empty: nominal + sim.errors.")
        errors_kind = declare("sim.errors", "paper",
                              "Sim: true errors when sim.true_robot is empty: 'paper' (+10 mm, +1 deg on every "
                              "parameter) or 'random' (uniform within those sizes, seeded).")
        seed = declare("sim.seed", 0, "Sim: random seed (errors, joint disturbance, reading noise).",
                       rule=parameters.non_negative)  # numpy's seeds are >= 0
        speed = declare("sim.joint_speed", 1.0, "Sim: maximum joint speed, rad/s.", rule=parameters.positive)
        tau = declare("sim.time_constant", 0.05, "Sim: settling time constant near the goal, s.",
                      rule=parameters.positive)
        disturbance = declare("sim.joint_disturbance", float(NoiseSpec().joint),
                              "Sim: half-width of the uniform joint disturbance drawn per goal, rad "
                              "(the paper's 0.1 deg).", rule=parameters.JOINT_NOISE)
        read_noise = declare("sim.read_noise", 0.0, "Sim: joint reading noise, rad (one sigma).",
                             rule=parameters.JOINT_NOISE)
        true_out = declare("sim.true_robot_out", "", "Sim: write the true robot model to this file (for evaluation); "
                           "one holding another true robot (a resumed session's) is refused.")

        # dynamixel
        port = declare("dynamixel.port", "/dev/ttyUSB0", "Dynamixel: serial port.")
        baud = declare("dynamixel.baudrate", 57600, "Dynamixel: baud rate.")
        ids = declare("dynamixel.ids", Parameter.Type.INTEGER_ARRAY, "Dynamixel: servo id per joint, base to tip.",
                      type_=Parameter.Type.INTEGER_ARRAY)
        tpr = declare("dynamixel.ticks_per_rad", Parameter.Type.DOUBLE_ARRAY,
                      "Dynamixel: ticks per rad per joint (sign gives the direction); default 4096/(2 pi).",
                      type_=Parameter.Type.DOUBLE_ARRAY)
        zero = declare("dynamixel.zero_ticks", Parameter.Type.INTEGER_ARRAY,
                       "Dynamixel: ticks at q = 0 per joint; default 2048.", type_=Parameter.Type.INTEGER_ARRAY)
        q_min = declare("dynamixel.min", Parameter.Type.DOUBLE_ARRAY,
                        "Dynamixel: lower joint limit per joint, rad; default the robot file's.",
                        type_=Parameter.Type.DOUBLE_ARRAY)
        q_max = declare("dynamixel.max", Parameter.Type.DOUBLE_ARRAY,
                        "Dynamixel: upper joint limit per joint, rad; default the robot file's.",
                        type_=Parameter.Type.DOUBLE_ARRAY)
        profile = declare("dynamixel.profile_velocity", 30,
                          "Dynamixel: Profile Velocity (units of 0.229 rev/min; 0 = no limit).")
        latency = declare("dynamixel.latency_timer_ms", 16.0, "Dynamixel: the USB adapter's latency timer, ms (FTDI's "
                          "default 16); the SDK waits twice this for a reply.", rule=parameters.positive)

        self.sim: SimArm | None = None
        if backend == "sim":
            rng = np.random.default_rng(seed)
            if true_path:
                true_robot = load_robot(true_path)
                if true_robot.n_joints != n:
                    raise parameters.NodeError(f"sim.true_robot {true_path}: {true_robot.n_joints} joints, "
                                           f"robot {robot_path} has {n}", 2)
            elif errors_kind in ("paper", "random"):
                true_robot = self.robot.with_errors(true_errors(self.robot, rng if errors_kind == "random" else None))
            else:
                raise parameters.NodeError(f"parameter sim.errors: expected 'paper' or 'random', got {errors_kind!r}", 2)
            if true_out:
                keep_truth(true_out, true_robot)
                save_robot(true_robot, true_out, header=f"True robot of the simulation: {robot_path} + "
                                                        f"sim.errors={errors_kind}, seed {seed}")
            self.sim = SimArm(true_robot, self.joint_names, rng, speed, tau, disturbance, read_noise)
            self.backend = self.sim
            from laser_calib_interfaces.msg import TrueSpots
            self.true_pub = self.create_publisher(TrueSpots, common.TRUE_SPOTS, common.STREAM_QOS)
        elif backend == "dynamixel":
            ids = list(ids or [])
            if not ids:
                raise parameters.NodeError("parameter dynamixel.ids: give one servo id per joint", 2)
            try:
                self.backend = dynamixel_backend(
                    port, baud, ids, list(tpr or [4096 / (2 * math.pi)] * n), list(zero or [2048] * n),
                    list(q_min or self.robot.q_min), list(q_max or self.robot.q_max), profile, self.joint_names,
                    latency)
            except ValueError as exc:
                raise parameters.NodeError(f"dynamixel parameters: {exc}", 2) from None
            except RuntimeError as exc:  # DynamixelError: one line naming the servo
                raise parameters.NodeError(str(exc), 1) from None
        else:
            raise parameters.NodeError(f"parameter backend: expected 'sim' or 'dynamixel', got {backend!r}", 2)

        try:
            self.state_pub = self.create_publisher(JointState, common.JOINT_STATES, common.STREAM_QOS)
            self.create_subscription(JointTrajectory, common.JOINT_TRAJECTORY, self.on_trajectory,
                                     common.COMMAND_QOS)
            self.status = ArmStatus(self, f"dynamixel {port}" if backend == "dynamixel" else backend)
            self.timer = self.create_timer(1.0 / rate, self.on_timer)
            self.exit_code = 0
            self.get_logger().info(f"{backend} arm '{self.robot.name}', {n} joints, publishing at {rate:g} Hz")
        except BaseException:  # a Ctrl-C included: common.run never gets this node to close the enabled arm
            self.close()
            raise

    def on_trajectory(self, msg: JointTrajectory) -> None:
        points = [TrajectoryPoint(list(p.positions), common.stamp_seconds(p.time_from_start),
                                  list(p.velocities), list(p.accelerations)) for p in msg.points]
        try:
            goal = trajectory_goal(list(msg.joint_names), points, self.joint_names, self.robot.q_min,
                                   self.robot.q_max, common.stamp_seconds(msg.header.stamp),
                                   common.now_ns(self) * 1e-9)
            self.backend.command(goal)
        except ValueError as exc:
            self.get_logger().error(f"joint_trajectory rejected: {exc}")
        except RuntimeError as exc:  # hardware fault: the backend has stopped the arm
            self.fail(str(exc))

    def on_timer(self) -> None:
        try:
            q, velocity = self.backend.read()
        except RuntimeError as exc:
            self.fail(str(exc))
            return
        stamp = self.get_clock().now().to_msg()
        msg = JointState()
        msg.header.stamp = stamp
        msg.name = self.joint_names
        msg.position = [float(v) for v in q]
        msg.velocity = [float(v) for v in velocity]
        self.state_pub.publish(msg)
        self.status.ok(f"{len(q)} joints read")
        if self.sim is not None:
            from laser_calib_interfaces.msg import TrueSpots
            spots, seen, beams = self.sim.true_spots()
            true = TrueSpots()
            true.header.stamp = stamp
            true.header.frame_id = common.SCREEN_FRAME
            true.spots = common.spots_to_msg(spots, seen)
            true.beams = [float(v) for v in np.where(seen[:, None], beams, 0.0).ravel()]
            self.true_pub.publish(true)

    def fail(self, message: str) -> None:
        """Hardware fault: the arm stopped, the fault on /diagnostics, then one line and exit code 1."""
        self.backend.stop()
        self.status.fault(f"{message}; arm stopped")
        raise parameters.NodeError(f"{message}; arm stopped", 1)

    def close(self) -> int:
        """Stop and release the arm; TORQUE_NOT_CONFIRMED (the exit code, see common.run) with one
        ERROR line naming the servos when some did not confirm torque off after the backend's
        retries: they may still hold torque, which the operator must know before touching the arm,
        and which a clean exit (launch: "process has finished cleanly") would hide."""
        backend = getattr(self, "backend", None)
        unconfirmed = backend.close() if backend is not None else []  # stops first
        if not unconfirmed:
            return 0
        ids = ", ".join(map(str, unconfirmed))
        self.get_logger().error(f"servo {ids} did not confirm torque off (write retried): it may still hold "
                                f"torque; secure the arm before approaching it")
        return TORQUE_NOT_CONFIRMED


def keep_truth(path: str, true_robot) -> None:
    """NodeError (exit 2) when ``path`` holds another true robot: a session resumed with other sim.errors
    or sim.seed measured its remaining poses on another arm, and the truth its report compares with was
    overwritten, unsaid."""
    try:
        written = load_robot(path)
    except InputError:  # none yet, or not a robot: this run's truth is written
        return
    if dump_robot(written) != dump_robot(true_robot):
        raise parameters.NodeError(f"sim.true_robot_out {path} holds another true robot (the session's, resumed "
                                   "with other sim.errors or sim.seed?): its poses were measured on that arm; give "
                                   "the session's simulation or another output folder", 2)


def main(args=None) -> int:
    return common.run(ArmDriver, args)


if __name__ == "__main__":
    sys.exit(main())
