"""The quaternion columns' order checked against the nominal model: a pose file whose
qw,qx,qy,qz hold quaternions in x,y,z,w order (ROS's geometry_msgs/Quaternion, scipy's
Rotation.as_quat, Eigen's coeffs()) is refused, not fitted.

Such a file is read as other rotations, of the same angles between poses (a permutation
of the components keeps every dot product of two quaternions), so nothing in the file
alone tells; fitted, it fails as NOT A CALIBRATION blaming the robot file, or on a short
chain passes with a model worse than the nominal one. Against the arm it shows: the
measured orientation of pose i is

    R_i = A N_i B        N_i (3,3) the nominal model's target orientation in the sensor frame,
                         A, B the errors of the sensor's and the target's frames

whatever A and B are (a frame guessed a turn off). For each reading of the columns the
best A, B (alternating orthogonal Procrustes, from several starts) leave each pose a
rotation error, the angle of (A N_i B)^T R_i. A reading that is right leaves the arm's
own errors and the sensor's noise: a few degrees at most (honest simulated files of the
paper's arms and the Panda's and Kinova's URDFs, errors within 10 mm / 1 deg, frames 30 deg
off their guesses: median at most 2.9 deg; the same files read as x,y,z,w: at least 11.9 deg).
The file is refused when the median as written exceeds MISFIT and the x,y,z,w
reading's is below MISFIT and RATIO times smaller. A one-joint chain's orientations
lie on one circle, which both readings fit exactly: no verdict there, and none is given.

The inverse rotations (JPL's quaternion convention, Hamilton's conjugate: qx, qy, qz
negated) are read too, and they always fit as well as the x,y,z,w order: a cyclic shift
of the four components is an odd permutation, an orthogonal map q -> a conj(q) b of
quaternions, that is the inverse rotation between two fixed frames, which A and B take
up. A file of inverse rotations was diagnosed as x,y,z,w order (0.362 deg against 0.363),
and the advice followed gave NOT A CALIBRATION, 197 mm RMS: the line names every reading
that fits, and says that the orientations alone cannot tell them apart.
"""

from __future__ import annotations

import numpy as np

from laser_calib.io.errors import InputError
from laser_calib.io.samples import Samples
from laser_calib.measurement.chain import chain_names, target_in_sensor
from laser_calib.measurement.frames import robot_frames
from laser_calib.measurement.rotations import quaternion_to_matrix
from laser_calib.model.robot import Robot

MISFIT = np.deg2rad(10.0)   # median rotation error no honest reading leaves (module docstring)
RATIO = 4.0                 # and the x,y,z,w reading fits at least this much better
SWEEPS = 30                 # alternating Procrustes steps per start
XYZW = [3, 0, 1, 2]         # the columns qw,qx,qy,qz as they hold x,y,z,w: w is the fourth


def check_quaternion_order(samples: Samples, robot: Robot, source: str) -> None:
    """One InputError naming the file's columns when its quaternions fit the nominal model only
    read in x,y,z,w order (module docstring); nothing for points or too few poses."""
    if samples.kind != "pose":
        return
    seen = samples.seen
    if seen.sum() < 3:
        return
    tips = samples.extra["tip"].astype(int) if "tip" in samples.extra else None
    nominal = target_in_sensor(robot, robot_frames(robot), samples.q[seen], np.zeros(len(chain_names(robot))),
                               tips=None if tips is None else tips[seen]).rotation
    quaternion = samples.quaternion[seen]
    group = np.zeros(int(seen.sum()), int) if tips is None else tips[seen]
    as_written = _median_misfit(quaternion_to_matrix(quaternion), nominal, group)
    if as_written <= MISFIT:
        return
    inverse = quaternion * np.array([1.0, -1.0, -1.0, -1.0])
    readings = {"in x,y,z,w order (ROS, scipy, Eigen; write them as w,x,y,z)": quaternion[:, XYZW],
                # (the inverse in x,y,z,w order is an even map, a rotation between fixed frames: it fits
                # exactly as the file as written does, so it is never read)
                "as the inverse rotations (JPL's convention; negate qx, qy, qz)": inverse}
    fitting = {what: misfit for what, values in readings.items()
               if (misfit := _median_misfit(quaternion_to_matrix(values), nominal, group))
               < min(MISFIT, as_written / RATIO)}
    if fitting:
        found = " or ".join(f"{what}: {np.degrees(misfit):.3g} deg" for what, misfit in fitting.items())
        raise InputError(f"{source}: fields qw,qx,qy,qz",
                         f"the orientations fit the arm only read otherwise (median rotation error "
                         f"{np.degrees(as_written):.3g} deg as written, the frames fitted each way; read {found})"
                         + (": the orientations alone cannot tell these apart; check how the file was written"
                            if len(fitting) > 1 else ""))


def _median_misfit(measured: np.ndarray, nominal: np.ndarray, group: np.ndarray) -> float:
    """The median over the poses of the rotation error (rad) that the best frames A, B of each
    tip's group leave: R_i (P,3,3) measured, N_i (P,3,3) nominal."""
    errors = np.concatenate([_misfit(measured[group == g], nominal[group == g]) for g in np.unique(group)])
    return float(np.median(errors))


def _misfit(measured: np.ndarray, nominal: np.ndarray) -> np.ndarray:
    """(P,) the rotation error of each pose under the best A, B of R_i = A N_i B over starts
    B = I and the half turns about x, y, z (one sweep can stall at a saddle a half turn away)."""
    best = None
    for start in (np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])):
        right = start
        for _ in range(SWEEPS):
            left = _nearest_rotation(np.einsum("pij,pkj->ik", measured, nominal @ right))      # sum R_i (N_i B)^T
            right = _nearest_rotation(np.einsum("pji,pjk->ik", left @ nominal, measured))     # sum (A N_i)^T R_i
        cosine = (np.einsum("pij,pij->p", left @ nominal @ right, measured) - 1.0) / 2.0
        errors = np.arccos(np.clip(cosine, -1.0, 1.0))
        if best is None or errors.sum() < best.sum():
            best = errors
    return best


def _nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    """The rotation nearest ``matrix`` (3,3) in the Frobenius norm (orthogonal Procrustes)."""
    u, _, vt = np.linalg.svd(matrix)
    return u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
