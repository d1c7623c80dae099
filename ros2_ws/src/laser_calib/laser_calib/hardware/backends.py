"""Arm backends behind one small protocol (ROS-free).

    command(q)        goal joint positions (N,) in rad; ValueError naming the joint if refused
    read()            -> (q (N,) rad, velocity (N,) rad/s), the joint readings
    stop()            stop safely (torque off on hardware); never raises; -> the ids of the
                      servos that did not confirm it (a safety matter the caller reports)
    close()           stop and release the device; idempotent; -> as stop()
    joint_names       (N,) names, base to tip

``SimArm`` is the true robot of the simulator; the Dynamixel backend is
laser_calib.hardware.dynamixel_arm.DynamixelArm, which has this protocol itself.
"""

from __future__ import annotations

import time
from typing import Callable, Protocol, Sequence

import numpy as np

from laser_calib.model.kinematics import predict
from laser_calib.model.robot import Robot
from laser_calib.sim.simulation import NoiseSpec


class ArmBackend(Protocol):
    joint_names: tuple[str, ...]

    def command(self, q: np.ndarray) -> None: ...

    def read(self) -> tuple[np.ndarray, np.ndarray]: ...

    def stop(self) -> list[int]: ...

    def close(self) -> list[int]: ...


class SimArm:
    """A simulated arm: the true robot (nominal + errors) moving its joints.

    Each joint reading moves towards the goal at most ``joint_speed`` rad/s and
    settles exponentially with ``time_constant`` s in the last
    ``joint_speed * time_constant`` rad, so velocity and position both tell when
    it has settled. The physical joint differs from its reading by a
    disturbance (the paper's joint error: backlash, compliance, encoder
    offset), drawn anew (uniform half-width ``disturbance``) for each goal and
    invisible to the reading. ``read_noise`` (rad, one sigma) adds encoder
    noise to each reading. The true spots are those of the true robot at the
    physical joints.
    """

    def __init__(self, true_robot: Robot, joint_names: Sequence[str], rng: np.random.Generator,
                 joint_speed: float = 1.0, time_constant: float = 0.05, disturbance: float = NoiseSpec().joint,
                 read_noise: float = 0.0, clock: Callable[[], float] = time.monotonic,
                 start: np.ndarray | None = None):
        if joint_speed <= 0 or time_constant <= 0:
            raise ValueError("joint_speed and time_constant must be positive")
        self.robot = true_robot
        self.joint_names = tuple(joint_names)
        if len(self.joint_names) != true_robot.n_joints:
            raise ValueError(f"{len(self.joint_names)} joint names for {true_robot.n_joints} joints")
        self.rng = rng
        self.speed = float(joint_speed)
        self.tau = float(time_constant)
        self.noise = NoiseSpec(joint=float(disturbance))
        self.read_noise = float(read_noise)
        self.clock = clock
        self.q = np.zeros(true_robot.n_joints) if start is None else np.array(start, float)
        self.velocity = np.zeros_like(self.q)
        self.goal = self.q.copy()
        self.disturbance = np.zeros_like(self.q)
        self._time = clock()
        self._stopped = False

    def command(self, q: np.ndarray) -> None:
        q = np.asarray(q, dtype=float)
        if q.shape != self.q.shape:
            raise ValueError(f"command has {q.size} joint positions, the arm has {self.q.size}")
        for name, value, low, high in zip(self.joint_names, q, self.robot.q_min, self.robot.q_max):
            if not low <= value <= high:  # also refuses NaN
                raise ValueError(f"{name}: goal {value:.6g} rad outside limits [{low:.6g}, {high:.6g}]")
        self._advance()
        self.goal = q.copy()
        self.disturbance = self.noise.draw(self.rng, self.noise.joint, q.shape)
        self._stopped = False

    def _advance(self) -> None:
        now = self.clock()
        dt = max(0.0, now - self._time)
        self._time = now
        if self._stopped or dt == 0.0:
            return
        error = self.goal - self.q
        sign = np.sign(error)
        far = np.abs(error) - self.speed * self.tau  # distance still to go at full speed
        t_full = np.clip(far / self.speed, 0.0, None)
        ramp = np.minimum(dt, t_full)
        remaining = np.where(far > 0, np.abs(error) - self.speed * ramp, np.abs(error))
        tail = dt - ramp  # time spent in the exponential tail
        remaining = np.where(remaining <= self.speed * self.tau + 1e-15, remaining * np.exp(-tail / self.tau),
                             remaining)
        self.q = self.goal - sign * remaining
        self.velocity = np.where(ramp >= dt, sign * self.speed, sign * remaining / self.tau)

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        self._advance()
        q = self.q.copy()
        if self.read_noise > 0:
            q += self.rng.normal(0.0, self.read_noise, q.shape)
        return q, self.velocity.copy()

    def true_joints(self) -> np.ndarray:
        """The physical joint angles (reading + disturbance) at the last read."""
        return self.q + self.disturbance

    def true_spots(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(spots (2,2) m, seen (2,), beams (2,3) unit directions in {0}): the two spots of the true robot at
        the physical joints, and their beams (the simulated camera draws an oblique beam's footprint)."""
        prediction = predict(self.robot, self.true_joints()[None])
        return prediction.spots[0], prediction.hit[0], prediction.state.beams[0]

    def stop(self) -> list[int]:
        self._advance()
        self.goal = self.q.copy()
        self.velocity[:] = 0.0
        self._stopped = True
        return []

    def close(self) -> list[int]:
        return self.stop()


def dynamixel_backend(port: str, baudrate: int, ids: Sequence[int], ticks_per_rad: Sequence[float],
                      zero_ticks: Sequence[int], q_min: Sequence[float], q_max: Sequence[float],
                      profile_velocity: int, joint_names: Sequence[str], latency_timer_ms: float = 16.0):
    """An opened DynamixelArm (laser_calib.hardware.dynamixel_arm) for the given joints."""
    from laser_calib.hardware.dynamixel_arm import DynamixelArm, DynamixelConfig, DynamixelJointConfig
    n = len(joint_names)
    for name, values in (("ids", ids), ("ticks_per_rad", ticks_per_rad), ("zero_ticks", zero_ticks),
                         ("min", q_min), ("max", q_max)):
        if len(values) != n:
            raise ValueError(f"dynamixel.{name} has {len(values)} entries, the arm has {n} joints")
    joints = tuple(DynamixelJointConfig(int(i), float(t), int(z), float(lo), float(hi))
                   for i, t, z, lo, hi in zip(ids, ticks_per_rad, zero_ticks, q_min, q_max))
    arm = DynamixelArm(DynamixelConfig(port, int(baudrate), joints, int(profile_velocity), float(latency_timer_ms)),
                       joint_names)
    arm.open()
    return arm
