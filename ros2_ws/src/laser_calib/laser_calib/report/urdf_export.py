"""The calibrated robot as a URDF: the source file with corrected joint origins.

Each movable joint's calibrated placement, origin · E(placement error) ·
Motion(axis, offset) (joint_chain.py), is one rigid transform: written as the
joint's new <origin xyz rpy>, the joint then moves from there by its reading
exactly as before, so the robot's forward kinematics in any URDF consumer
(robot_state_publisher, MoveIt, ros2_control's controllers) are the calibrated
model's. Everything else in the file (links, meshes, limits, ros2_control and
gazebo tags, comments) is kept as it was: the XML is edited in place (lxml), not
re-serialised through a URDF model. From a .xacro source the output is the
expanded URDF (macros cannot be corrected in place; the corrections list says
which origins to change in the xacro).

corrections(robot, identifiable) is the machine-readable list: per movable
joint the nominal and calibrated origin and the 7 estimated values, with the
values the data could not determine marked held (null), never as numbers.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from lxml import etree
from scipy.spatial.transform import Rotation

from laser_calib.measurement.frames import Pose
from laser_calib.model.joint_chain import OFFSET, PLACEMENT, PLACEMENT_PARAMS, PRISMATIC
from laser_calib.model.robot import Robot


def _transform(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rotation, translation
    return out


def calibrated_origins(robot: Robot) -> dict[str, np.ndarray]:
    """Joint name -> calibrated origin (4,4) of each movable joint of the chain."""
    chain = robot.chain
    out = {}
    for j in chain.movable:
        joint = chain.joints[j]
        values = chain.values[chain.block(j):chain.block(j) + len(PLACEMENT_PARAMS)]
        placed = Pose(joint.origin[:3, :3], joint.origin[:3, 3]).perturbed(values[PLACEMENT])
        motion = np.eye(4)
        if joint.kind == PRISMATIC:
            motion[:3, 3] = joint.axis * values[OFFSET]
        else:
            motion[:3, :3] = Rotation.from_rotvec(joint.axis * values[OFFSET]).as_matrix()
        out[joint.name] = _transform(placed.rotation, placed.translation) @ motion
    return out


def origin_attributes(transform: np.ndarray) -> dict[str, str]:
    """URDF xyz and rpy (R = Rz(yaw) Ry(pitch) Rx(roll)) at full precision."""
    rpy = Rotation.from_matrix(transform[:3, :3]).as_euler("xyz")
    return {"xyz": " ".join(repr(float(v)) for v in transform[:3, 3]),
            "rpy": " ".join(repr(float(v)) for v in rpy)}


def calibrated_urdf(robot: Robot) -> str:
    """The robot's URDF text with each movable joint's origin replaced by its calibrated one."""
    root = etree.fromstring(robot.chain.urdf.encode(), etree.XMLParser(remove_blank_text=False))
    origins = calibrated_origins(robot)
    for element in root.iter("joint"):
        name = element.get("name")
        if name not in origins or element.getparent() is not root:
            continue
        origin = element.find("origin")
        if origin is None:
            origin = etree.SubElement(element, "origin")
        for key, value in origin_attributes(origins[name]).items():
            origin.set(key, value)
    return etree.tostring(root, encoding="unicode", xml_declaration=False) + "\n"


def corrections(robot: Robot, nominal: Robot, identifiable: np.ndarray | None = None) -> list[dict]:
    """Per movable joint: nominal and calibrated origin, and the estimated
    placement error and offset (m, rad) with None where not identifiable."""
    chain = robot.chain
    free = np.ones(chain.n_params, bool) if identifiable is None else np.asarray(identifiable[:chain.n_params])
    before, after = calibrated_origins(nominal), calibrated_origins(robot)
    out = []
    for j in chain.movable:
        joint = chain.joints[j]
        b = chain.block(j)
        values = {p: (float(chain.values[b + k]) if free[b + k] else None) for k, p in enumerate(PLACEMENT_PARAMS)}
        out.append({"joint": joint.name, "type": joint.kind,
                    "nominal_origin": origin_attributes(before[joint.name]),
                    "calibrated_origin": origin_attributes(after[joint.name]),
                    "errors": values, "units": {"offset": "m" if joint.kind == PRISMATIC else "rad", "x": "m",
                                                "y": "m", "z": "m", "rx": "rad", "ry": "rad", "rz": "rad"}})
    return out


def save_calibrated_urdf(calibrated: Robot, nominal: Robot, identifiable: np.ndarray, folder: Path,
                         source: str) -> tuple[str, str]:
    """robot_calibrated.urdf and urdf_corrections.json (with the fitted frames) in folder."""
    folder = Path(folder)
    (folder / "robot_calibrated.urdf").write_text(calibrated_urdf(calibrated))
    data = {"source": source, "base": calibrated.chain.base, "tips": list(calibrated.chain.tip_links),
            "joints": corrections(calibrated, nominal, identifiable),
            "frames": calibrated.extra.get("frames", {})}
    (folder / "urdf_corrections.json").write_text(json.dumps(data, indent=2))
    return "robot_calibrated.urdf", "urdf_corrections.json"
