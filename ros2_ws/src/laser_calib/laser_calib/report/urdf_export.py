"""The calibrated robot as a URDF: the source file with corrected joint origins
(calibrated_urdf, model/urdf.py), and the list of the corrections.

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

from laser_calib.model.fit_marks import fit_marks
from laser_calib.model.joint_chain import PLACEMENT_PARAMS, PRISMATIC
from laser_calib.model.robot import Robot
from laser_calib.model.urdf import calibrated_origins, calibrated_urdf, origin_attributes


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
                         source: str, failure: str | None = None, caution: str | None = None) -> tuple[str, str]:
    """robot_calibrated.urdf and urdf_corrections.json (with the fitted frames) in folder.
    failure: why the fit is no calibration (estimation/failures.py); caution: poses it never saw
    say it is worse than the robot as designed; both said in both files: the tools that load a
    URDF show no console."""
    folder = Path(folder)
    text = calibrated_urdf(calibrated)
    said = fit_marks(failure, caution)
    if said:
        declaration = text.index("?>") + 2 if text.startswith("<?xml") else 0
        text = (text[:declaration] + "".join(f"\n<!-- {line.replace('--', '- -')} -->" for line in said)
                + text[declaration:])
    (folder / "robot_calibrated.urdf").write_text(text)
    data = {"source": source, "failure": failure, "caution": caution, "base": calibrated.chain.base,
            "tips": list(calibrated.chain.tip_links),
            "joints": corrections(calibrated, nominal, identifiable),
            "frames": calibrated.extra.get("frames", {})}
    (folder / "urdf_corrections.json").write_text(json.dumps(data, indent=2))
    return "robot_calibrated.urdf", "urdf_corrections.json"
