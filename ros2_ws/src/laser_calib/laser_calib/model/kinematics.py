"""Forward model, beam-screen intersection and the differential kinematics.

The chain from frame {0} to a laser is a sequence of elementary transforms
Trans(axis, v) / Rot(axis, v); each D-H value is the argument of exactly one of
them (eq. 2). A small error in that value moves the laser frame by a twist
(paper eq. 5): a translation error by (u, 0), a rotation error by
(u x (p_laser - o), u), with u the axis and o the origin of the frame just
before the transform. Stacking these twists over the parameters gives Jac_1
(eq. 6, 6 x (4N+5) per pose, whose 6x4 blocks are the per-link matrices);
Jac_2 (eq. 11, 2x6) maps a twist of the laser frame to the motion of its spot
on the screen x = 0, and the measurement Jacobian is their product (eq. 12).
Everything is vectorised over poses P and lasers L.

The same machinery serves a chain of joint placements (URDF, joint_chain.py):
its transforms are about / along any unit axis, with fixed transforms (the
origins) between them, and a joint's value may be a linear function of a
reading (mimic). A robot without lasers ends at its last link (no SLM).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from laser_calib.model.joint_chain import OFFSET, PRISMATIC
from laser_calib.model.robot import PAPER, Robot

X, Y, Z = 0, 1, 2
TRANS, ROT, FIXED = 0, 1, 2
DH_READING = (1.0, 0.0)  # a D-H joint's value is theta0 + 1 * q + 0


@dataclass(frozen=True, eq=False)
class Op:
    """One elementary transform of the chain.

    kind TRANS / ROT: along / about ``axis`` (0, 1, 2 for x, y, z of the frame
    before it, or a unit vector (3,) in that frame) by params[index], plus for a
    joint multiplier * q[:, reading] + constant (reading -1: none). FIXED: the
    constant transform ``fixed`` (4,4), no parameter.
    """

    kind: int
    axis: int | np.ndarray = X
    index: int = -1
    reading: int = -1
    multiplier: float = 1.0
    constant: float = 0.0
    records: bool = False  # this op is a read joint: its origin and axis go to joint_origin / joint_axis
    fixed: np.ndarray | None = None


def _dh_ops(robot: Robot) -> list[Op]:
    ops = []
    for i in range(robot.n_joints):
        a, d, alpha, theta = 4 * i, 4 * i + 1, 4 * i + 2, 4 * i + 3
        read = Op(ROT, Z, theta, i, *DH_READING, records=True)
        d_op, theta_op = Op(TRANS, Z, d), read
        if robot.joints[i].prismatic:
            d_op, theta_op = Op(TRANS, Z, d, i, *DH_READING, records=True), Op(ROT, Z, theta)
        if robot.convention == PAPER:
            ops += [Op(TRANS, X, a), d_op, Op(ROT, X, alpha), theta_op]
        else:  # standard D-H: Trans(z,d) Rot(z,theta) Trans(x,a) Rot(x,alpha)
            ops += [d_op, theta_op, Op(TRANS, X, a), Op(ROT, X, alpha)]
    return ops


def _placement_ops(robot: Robot, tip: int) -> list[Op]:
    """Origin, placement error and motion of each joint from the base to tip ``tip``."""
    chain = robot.chain
    ops = []
    for j in chain.tips[tip]:
        joint = chain.joints[j]
        ops.append(Op(FIXED, fixed=joint.origin))
        if not joint.movable:
            continue
        b = chain.block(j)  # b + OFFSET, then the placement x, y, z, rx, ry, rz
        ops += [Op(TRANS, X, b + 1), Op(TRANS, Y, b + 2), Op(TRANS, Z, b + 3),
                Op(ROT, X, b + 4), Op(ROT, Y, b + 5), Op(ROT, Z, b + 6)]
        ops.append(Op(TRANS if joint.kind == PRISMATIC else ROT, joint.axis, b + OFFSET, joint.reading,
                      joint.multiplier, joint.mimic_offset, records=not joint.coupled))
    return ops


def chain_ops(robot: Robot, tip: int = 0) -> list[Op]:
    """The elementary transforms from the base to the SLM (or the tip without one).

    A D-H joint's angle transform has parameter index 4i+3 (theta0_i) and q_i
    added to it (a prismatic joint's: d_i, index 4i+1); a chain of joint placements (joint_chain.py) has per joint its
    origin, 6 placement errors and the motion by offset + reading.
    """
    ops = _dh_ops(robot) if robot.chain is None else _placement_ops(robot, tip)
    if robot.slm is not None:
        s = robot.n_link_params
        ops += [Op(TRANS, X, s), Op(TRANS, Z, s + 1), Op(ROT, X, s + 2), Op(ROT, Y, s + 3), Op(ROT, Z, s + 4)]
    return ops


def _rotate(rotation: np.ndarray, axis: int | np.ndarray, angle: np.ndarray | float) -> np.ndarray:
    """rotation @ Rot(axis, angle) with the pose axis last: rotation (3,3,P)
    (rotation[:, i] is column i, (3,P)), angle (P,) or a scalar; axis 0/1/2 or a
    unit vector (3,) (Rodrigues)."""
    c, s = np.cos(angle), np.sin(angle)
    if not isinstance(axis, int):
        k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
        turn = np.eye(3)[..., None] + np.multiply.outer(k, s) + np.multiply.outer(k @ k, 1 - c)   # (3,3,P)
        return np.einsum("aip,ijp->ajp", rotation, np.broadcast_to(turn, (3, 3, rotation.shape[2])))
    i, j = {X: (1, 2), Y: (2, 0), Z: (0, 1)}[axis]
    out = np.empty(rotation.shape)
    out[:, axis] = rotation[:, axis]
    np.multiply(c, rotation[:, i], out=out[:, i])
    out[:, i] += s * rotation[:, j]
    np.multiply(c, rotation[:, j], out=out[:, j])
    out[:, j] -= s * rotation[:, i]
    return out


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b along axis 1 of (K,3,P) stacks (np.cross moves the axis and copies twice)."""
    out = np.empty_like(a)
    for i, j, k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        np.subtract(a[:, j] * b[:, k], a[:, k] * b[:, j], out=out[:, i])
    return out


def rot_x(angle: float) -> np.ndarray:
    return _rotate(np.eye(3)[..., None], X, angle)[..., 0]


def rot_y(angle: float) -> np.ndarray:
    return _rotate(np.eye(3)[..., None], Y, angle)[..., 0]


@dataclass(frozen=True)
class ChainState:
    """The arm at P poses.

    origin (P,3): SLM origin in {0}, which is also every laser's origin;
    rotation (P,3,3): SLM frame; beams (P,L,3): unit beam directions;
    joint_origin, joint_axis (P,N,3): origin and axis (of rotation, or of
    translation for a prismatic joint) of each read joint, NaN for a reading
    that does not move this tip (another arm of a tree);
    twists (P,6,n) or None: Jac_1, the motion (v; w) of the laser frame per unit
    error of each parameter (eq. 6).
    """

    origin: np.ndarray
    rotation: np.ndarray
    beams: np.ndarray
    joint_origin: np.ndarray
    joint_axis: np.ndarray
    twists: np.ndarray | None


@dataclass(frozen=True)
class _Walk:
    """One pass along the chain, pose axis last: origin (3,P), rotation (3,3,P),
    joint_origin, joint_axis (N,3,P); per elementary transform its axis u (3,P)
    and, for a rotation, the origin o (3,P) before it (what eq. 5 needs), with
    the parameter index of each: trans (Kt,), rots (Kr,)."""

    origin: np.ndarray
    rotation: np.ndarray
    joint_origin: np.ndarray
    joint_axis: np.ndarray
    trans: list[int]
    trans_axes: list[np.ndarray]
    rots: list[int]
    rot_axes: list[np.ndarray]
    bases: list[np.ndarray]


def _walk(robot: Robot, q: np.ndarray, errors: np.ndarray | None, tip: int, record: bool = True) -> _Walk:
    """Forward kinematics with the pose axis last (each component a contiguous
    (P,) row, so an elementary transform is a few vector operations), recording
    (``record``: for the Jacobians) each transform's axis and origin (views: no
    array is changed in place, so each keeps its rotation alive)."""
    n_poses = q.shape[0]
    params = robot.vector() if errors is None else robot.vector() + np.asarray(errors, float)   # (n,) or (P,n)
    readings = q.T                                                                              # (N,P)

    rotation = np.broadcast_to(np.eye(3)[..., None], (3, 3, n_poses))   # (3,3,P)
    origin = np.zeros((3, n_poses))
    joint_origin = np.full((robot.n_joints, 3, n_poses), np.nan)
    joint_axis = np.full((robot.n_joints, 3, n_poses), np.nan)
    walk = _Walk(origin, rotation, joint_origin, joint_axis, [], [], [], [], [])
    for op in chain_ops(robot, tip):
        if op.kind == FIXED:
            origin = origin + np.einsum("aip,i->ap", rotation, op.fixed[:3, 3])
            rotation = np.einsum("aip,ij->ajp", rotation, op.fixed[:3, :3])
            continue
        value = params[..., op.index]
        if op.reading >= 0:
            value = value + (op.multiplier * readings[op.reading] + op.constant)
        u = rotation[:, op.axis] if isinstance(op.axis, int) else np.einsum("aip,i->ap", rotation, op.axis)
        if op.records:
            joint_origin[op.reading] = origin
            joint_axis[op.reading] = u
        if op.kind == TRANS:
            if record:
                walk.trans.append(op.index)
                walk.trans_axes.append(u)
            origin = origin + u * value
        else:
            if record:
                walk.rots.append(op.index)
                walk.rot_axes.append(u)
                walk.bases.append(origin)
            rotation = _rotate(rotation, op.axis, value)
    return replace(walk, origin=origin, rotation=rotation)


def _beams(robot: Robot, rotation: np.ndarray) -> np.ndarray:
    """(L,3,P) unit beam directions in {0} from the SLM rotation (3,3,P)."""
    laser_rotations = [rot_x(g) @ rot_y(b) for g, b in robot.laser_angles()]
    if not laser_rotations:
        return np.zeros((0, 3, rotation.shape[2]))
    return np.stack([np.einsum("aip,i->ap", rotation, r[:, 2]) for r in laser_rotations])


def forward(robot: Robot, q: np.ndarray, errors: np.ndarray | None = None, twists: bool = False,
            tip: int = 0) -> ChainState:
    """Forward kinematics at joint readings q (P,N) with errors (n,) or (P,n);
    ``tip``: which tip of a tree of joint placements. The outputs are the
    pose-first shapes of ChainState."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    walk = _walk(robot, q, errors, tip, twists)
    jac1 = None
    if twists:
        columns = np.zeros((robot.n_params, 6, q.shape[0]))                 # Jac_1 with the pose axis last
        if walk.trans:
            columns[walk.trans, :3] = np.stack(walk.trans_axes)
        u = np.stack(walk.rot_axes)                                        # (K,3,P)
        lever = walk.origin - np.stack(walk.bases)                         # p_laser - o
        columns[walk.rots, :3] = _cross(u, lever)
        columns[walk.rots, 3:] = u
        jac1 = np.ascontiguousarray(columns.transpose(2, 1, 0))
    return ChainState(walk.origin.T.copy(), np.ascontiguousarray(walk.rotation.transpose(2, 0, 1)),
                      np.ascontiguousarray(_beams(robot, walk.rotation).transpose(2, 0, 1)),
                      np.ascontiguousarray(walk.joint_origin.transpose(2, 0, 1)),
                      np.ascontiguousarray(walk.joint_axis.transpose(2, 0, 1)), jac1)


@dataclass(frozen=True)
class Spots:
    """Beam-screen intersections: k (P,L) beam length, yz (P,L,2) spot in m,
    hit (P,L) k > 0 and inside the screen."""

    k: np.ndarray
    yz: np.ndarray
    hit: np.ndarray


def intersect(robot: Robot, state: ChainState) -> Spots:
    """Spots on the screen x = 0 (eq. 8): k = -p_x / z_x, spot = p + k z."""
    p = state.origin[:, None, :]
    z = state.beams
    with np.errstate(divide="ignore", invalid="ignore"):
        k = -p[..., 0] / z[..., 0]
        spot = p + k[..., None] * z
    yz = spot[..., 1:]
    finite = np.isfinite(k) & np.isfinite(yz).all(axis=-1)
    hit = (finite & (k > 0)
           & (np.abs(yz[..., 0]) <= robot.screen.half_y) & (np.abs(yz[..., 1]) <= robot.screen.half_z))
    return Spots(k=k, yz=yz, hit=hit)


def spot_jacobian(state: ChainState, spots: Spots) -> np.ndarray:
    """Jac_2 (eq. 11), (P,L,2,6): spot motion (dy, dz) per twist (v; w) of the laser frame.

    d spot = Pi (dv + k dw x z) with Pi = I - z e_x^T / z_x keeping the spot on x = 0.
    """
    z = state.beams
    k = spots.k
    with np.errstate(divide="ignore", invalid="ignore"):
        projection = np.eye(3) - z[..., :, None] * (np.array([1.0, 0.0, 0.0]) / z[..., 0:1])[..., None, :]
    # dw x z = -[z]x dw
    skew = np.zeros(z.shape[:-1] + (3, 3))
    skew[..., 0, 1], skew[..., 0, 2] = -z[..., 2], z[..., 1]
    skew[..., 1, 0], skew[..., 1, 2] = z[..., 2], -z[..., 0]
    skew[..., 2, 0], skew[..., 2, 1] = -z[..., 1], z[..., 0]
    motion = np.concatenate([np.broadcast_to(np.eye(3), skew.shape), -k[..., None, None] * skew], axis=-1)
    return (projection @ motion)[..., 1:, :]


@dataclass(frozen=True)
class Prediction:
    """Predicted spots (P,L,2) with their hit mask (P,L), beam lengths k (P,L), and
    optionally the measurement Jacobian (P,L,2,n) (eq. 12) and the chain state."""

    spots: np.ndarray
    hit: np.ndarray
    k: np.ndarray
    jacobian: np.ndarray | None
    state: ChainState


def usable(robot: Robot, prediction: Prediction, margin: float) -> np.ndarray:
    """(P,) poses a plan can ask for: every beam on the screen at least ``margin`` m inside its
    edge, and the arm on its own side of the screen. A beam meets the screen forward (k > 0)
    from either side, but an arm cannot reach through it: a UR10e standing 1 m in front of the
    screen was planned with its laser module 0.16 m behind it. The arm's side is that of its
    first joint (an arm whose first joint lies in the screen's plane has none)."""
    spots = prediction.spots
    inside = (prediction.hit & (np.abs(spots[..., 0]) <= robot.screen.half_y - margin)
              & (np.abs(spots[..., 1]) <= robot.screen.half_z - margin)).all(axis=1)
    state = prediction.state
    points = np.concatenate([state.joint_origin[..., 0], state.origin[:, None, 0]], axis=1)   # (P,N+1) x
    first = np.argmax(np.isfinite(points), axis=1)            # NaN: a joint of another arm of a tree
    side = np.nan_to_num(np.sign(points[np.arange(len(points)), first]))
    return inside & ((side[:, None] * points > 0) | np.isnan(points) | (side[:, None] == 0)).all(axis=1)


def predict(robot: Robot, q: np.ndarray, errors: np.ndarray | None = None, jacobian: bool = False) -> Prediction:
    q = np.atleast_2d(np.asarray(q, dtype=float))
    walk = _walk(robot, q, errors, 0, jacobian)
    beams = _beams(robot, walk.rotation)                                   # (L,3,P)
    # what the spots need pose-first; the rest as views (its callers rarely look)
    state = ChainState(walk.origin.T.copy(), walk.rotation.transpose(2, 0, 1),
                       np.ascontiguousarray(beams.transpose(2, 0, 1)), walk.joint_origin.transpose(2, 0, 1),
                       walk.joint_axis.transpose(2, 0, 1), None)
    spots = intersect(robot, state)
    jac = _spot_jacobian(robot, walk, beams, spots.k.T) if jacobian else None
    return Prediction(spots.yz, spots.hit, spots.k, jac, state)


def _spot_jacobian(robot: Robot, walk: _Walk, beams: np.ndarray, k: np.ndarray) -> np.ndarray:
    """The measurement Jacobian (P,L,2,n) (eq. 12) without forming Jac_1: a
    translation along u moves the spot point s = p + k z (3-D, on the screen)
    by u, a rotation about u through o by u x (s - o) (the twist (u x (p - o), u)
    of eq. 5 carried along the beam: u x (p - o) + k u x z); Jac_2's projection
    Pi = I - z e_x^T / z_x (eq. 11) keeps its (y, z) rows: (Pi m)_i = m_i - (z_i / z_x) m_x.
    beams (L,3,P), k (L,P): pose axis last, so each step is a few vector operations."""
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = beams[:, 1:] / beams[:, :1]                                # (L,2,P) z_i / z_x
        spot = walk.origin + k[:, None] * beams                            # (L,3,P)
    jac = np.zeros((len(beams), 2, robot.n_params, beams.shape[2]))        # (L,2,n,P)
    if walk.trans:
        u = np.stack(walk.trans_axes)                                      # (Kt,3,P)
        jac[:, :, walk.trans] = u[:, 1:].transpose(1, 0, 2) - slope[:, :, None] * u[:, 0]
    if walk.rots:
        u = np.stack(walk.rot_axes)                                        # (Kr,3,P)
        bases = np.stack(walk.bases)
        for laser, s in enumerate(spot):
            motion = _cross(u, s - bases)                                  # (Kr,3,P)
            jac[laser][:, walk.rots] = (motion[:, 1:] - slope[laser] * motion[:, :1]).transpose(1, 0, 2)
    return np.ascontiguousarray(jac.transpose(3, 0, 1, 2))


def joint_columns(robot: Robot) -> np.ndarray:
    """Indices of the theta errors (the offsets of a chain's read joints): the
    measurement Jacobian's columns for dq_i too, when no joint is coupled; -1
    for a chain's reading that only drives a mimic joint (no offset of its own)."""
    if robot.chain is None:
        return np.array([4 * i + (1 if j.prismatic else 3) for i, j in enumerate(robot.joints)], dtype=int)
    by_name = {j.name: i for i, j in enumerate(robot.chain.joints)}
    return np.array([robot.chain.block(by_name[name]) + OFFSET if name in by_name else -1
                     for name in robot.chain.readings], dtype=int)


def joint_jacobian(robot: Robot, jac: np.ndarray) -> np.ndarray:
    """d predicted / d q (..., N) from the parameter Jacobian (..., n): a reading
    moves its joint's offset, and each joint coupled to it by its multiplier."""
    columns = joint_columns(robot)
    out = np.where(columns >= 0, jac[..., columns], 0.0)
    if robot.chain is not None:
        for j in robot.chain.movable:
            joint = robot.chain.joints[j]
            if joint.coupled:
                out[..., joint.reading] += joint.multiplier * jac[..., robot.chain.block(j) + OFFSET]
    return out
