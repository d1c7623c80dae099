"""A robot from a URDF (or xacro) description: the joint placements from a base
link to one or more tip links (joint_chain.py).

Parsed with yourdfpy (maintained, pure Python, reads every URDF element and
keeps mimic and limits; urdfdom-py is not on PyPI for Python 3.12) once
urdf_checks.py has checked the text (urdf_text.py reads it: encoding, xacro). The URDF text itself is kept in the chain, so
the calibrated description can be written as the same file with corrected
origins (calibrated_urdf; report/urdf_export.py adds the list of corrections).
The ROS nodes get the text from the /robot_description topic:
robot_from_urdf(text, base, tip). A robot YAML names the URDF with ``urdf:``
and adds the lasers (robot_file.py, docs/urdf.md).

Joint readings q are the read (non-mimic) movable joints, in the order they are
met walking from the base to each tip in turn; then each mimic joint's source
that is not itself on the way (its reading drives the mimic joint).
"""

from __future__ import annotations

import io
import math
import warnings
from dataclasses import replace
from pathlib import Path
from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from laser_calib.io.errors import InputError
from laser_calib.measurement.frames import Pose
from laser_calib.model.fit_marks import is_fit_mark, refuse_failed_urdf
from laser_calib.model.joint_chain import (FIXED_JOINT, OFFSET, PLACEMENT, PLACEMENT_PARAMS, PRISMATIC, REVOLUTE,
                                           UNLIMITED, ChainJoint, JointChain)
from laser_calib.model.robot import (LIMIT_ANGLE, LIMIT_TRAVEL, Laser, Robot, Screen, Slm, plausible_angle,
                                     plausible_length)
from laser_calib.model.urdf_checks import check_tree
from laser_calib.model.urdf_text import urdf_text

URDF_SUFFIXES = (".urdf", ".xacro", ".xml")  # in any case: ARM.URDF, and older descriptions named .xml
_KINDS = {"revolute": REVOLUTE, "continuous": REVOLUTE, "prismatic": PRISMATIC, "fixed": FIXED_JOINT}
def _parse(text: str, source: str):
    import yourdfpy
    from lxml import etree

    try:  # strict XML first: yourdfpy would fall back to a lenient parse of a broken file
        root = etree.fromstring(text.encode())
    except etree.XMLSyntaxError as exc:
        raise InputError(f"{source}: line {exc.lineno}", f"not valid XML ({exc.msg})") from None
    check_tree(root, source)
    try:
        return yourdfpy.URDF.load(io.BytesIO(text.encode()), build_scene_graph=False, load_meshes=False)
    except Exception as exc:  # lxml and yourdfpy raise many types for a broken file
        raise InputError(source, f"not a valid URDF ({exc})") from None


def _path(joints_by_child: dict, base: str, tip: str, source: str) -> list:
    """The URDF joints from base to tip."""
    path, link, seen = [], tip, set()
    while link != base:
        if link not in joints_by_child:
            raise InputError(source, f"link '{tip}' is not below link '{base}'")
        if link in seen:  # check_tree refuses loops; a walk up must end whatever it is given
            raise InputError(source, f"kinematic loop (link '{link}' is its own ancestor)")
        seen.add(link)
        joint = joints_by_child[link]
        path.append(joint)
        link = joint.parent
    return path[::-1]


def _chain_joint(joint, source: str, rpy: float = 0.0) -> ChainJoint:
    """``rpy``: the largest |roll|, |pitch|, |yaw| as written in the joint's origin (units check)."""
    where = f"{source}: joint '{joint.name}'"
    if joint.type not in _KINDS:
        raise InputError(where, f"type '{joint.type}' cannot be calibrated (revolute, continuous, prismatic, "
                                "fixed): choose base and tip links with no such joint between them")
    origin = np.eye(4) if joint.origin is None else np.asarray(joint.origin, float)
    axis = np.asarray(joint.axis if joint.axis is not None else (1.0, 0.0, 0.0), float)
    norm = np.linalg.norm(axis)
    if _KINDS[joint.type] != FIXED_JOINT and not (np.isfinite(norm) and norm > 0):
        raise InputError(f"{where}: axis", f"expected a non-zero axis, got {axis.tolist()}")
    # The spec requires a revolute or prismatic joint's <limit>, its missing lower / upper 0:
    # a joint the file holds still is a mistake on the chain (off it, no concern of ours).
    limited = joint.type in ("revolute", "prismatic")
    bounds = (None, None) if joint.limit is None else (joint.limit.lower, joint.limit.upper)
    if limited and not all(bound is not None and math.isfinite(bound) for bound in bounds):
        raise InputError(f"{where}: limit", f"a {joint.type} joint needs finite <limit lower=\"...\" upper=\"...\"> "
                                            "(a missing one is 0 in the URDF spec, holding it still), got " +
                                            ", ".join(f"{key} {'none' if bound is None else bound}"
                                                      for key, bound in zip(("lower", "upper"), bounds)))
    missing = [] if joint.limit is None else [key for key in ("effort", "velocity") if getattr(joint.limit, key) is None]
    if missing:
        raise InputError(f"{where}: limit", f"missing attribute {' and '.join(map(repr, missing))}: urdfdom "
                                            "(robot_state_publisher, RViz, MoveIt) refuses a <limit> without effort "
                                            "and velocity, and the calibrated URDF would carry it")
    lower, upper = (float(bounds[0]), float(bounds[1])) if limited else (-UNLIMITED, UNLIMITED)
    if lower >= upper and _KINDS[joint.type] != FIXED_JOINT:
        raise InputError(f"{where}: limit", f"lower {lower} is not below upper {upper}")
    _check_units(where, joint, origin, rpy, (lower, upper) if limited else ())
    return ChainJoint(joint.name, _KINDS[joint.type], origin, axis / (norm if norm > 0 else 1.0),
                      lower=lower, upper=upper)


def _check_units(where: str, joint, origin: np.ndarray, rpy: float, limits: tuple[float, ...]) -> None:
    """One line for a length in mm or an angle in degrees (URDF is in metres and radians)."""
    plausible_length(f"{where}: origin xyz", float(np.abs(origin[:3, 3]).max()))
    plausible_angle(f"{where}: origin rpy", rpy)
    for side, bound in zip(("lower", "upper"), limits):
        if joint.type == "prismatic":
            plausible_length(f"{where}: limit {side}", bound, LIMIT_TRAVEL, "prismatic limit")
        else:
            plausible_angle(f"{where}: limit {side}", bound, LIMIT_ANGLE)


def _written_rpy(text: str) -> dict[str, float]:
    """Joint name -> the largest |roll|, |pitch|, |yaw| of its origin as written
    (yourdfpy keeps the matrix only, in which 90 read as radians is a rotation too)."""
    from lxml import etree

    out = {}
    for element in etree.fromstring(text.encode()).iter("joint"):
        origin = element.find("origin")
        try:
            out[element.get("name")] = max(abs(float(v)) for v in origin.get("rpy", "0").split())
        except (AttributeError, ValueError):  # no origin (a transmission's joint), or yourdfpy's to judge
            continue
    return out


def chain_from_urdf(urdf, text: str, base: str, tips: Sequence[str], source: str) -> JointChain:
    """The joint placements from ``base`` to each of ``tips`` (link names) of a
    parsed yourdfpy.URDF ``urdf`` whose text is ``text``."""
    by_child = {j.child: j for j in urdf.robot.joints}
    by_name = {j.name: j for j in urdf.robot.joints}
    links = {link.name for link in urdf.robot.links}
    for link in (base, *tips):
        if link not in links:
            raise InputError(source, f"no link '{link}' (links: {', '.join(sorted(links))})")
    order: list[str] = []
    tip_paths = []
    for tip in tips:
        path = _path(by_child, base, tip, source)
        for joint in path:
            if joint.name not in order:
                order.append(joint.name)
        tip_paths.append(tuple(order.index(j.name) for j in path))
    rpy = _written_rpy(text)
    mimics = {name: by_name[name].mimic for name in order if by_name[name].mimic is not None}
    readings = [n for n in order if _KINDS.get(by_name[n].type) not in (None, FIXED_JOINT) and n not in mimics]
    for name, mimic in mimics.items():
        source_joint = by_name.get(mimic.joint)
        if source_joint is None or source_joint.mimic is not None or _KINDS.get(source_joint.type) in (None,
                                                                                                   FIXED_JOINT):
            raise InputError(f"{source}: joint '{name}': mimic", f"'{mimic.joint}' is not a driven joint")
        if not all(math.isfinite(value) for value in (mimic.multiplier, mimic.offset) if value is not None):
            raise InputError(f"{source}: joint '{name}': mimic", f"expected a finite multiplier and offset, got "
                                                                 f"{mimic.multiplier} and {mimic.offset}")
    # A source off the way (a gripper's other finger, a torso joint above the base) is read
    # for its mimic joint only: it has a reading and limits, no placement in this chain.
    off_way = [n for n in dict.fromkeys(m.joint for m in mimics.values()) if n not in readings]
    sources = tuple(_chain_joint(by_name[n], source, rpy.get(n, 0.0)) for n in off_way)
    readings += [joint.name for joint in sources]
    sources = tuple(replace(joint, reading=readings.index(joint.name)) for joint in sources)
    joints = []
    for name in order:
        joint = _chain_joint(by_name[name], source, rpy.get(name, 0.0))
        if name in mimics:
            m = mimics[name]
            joint = replace(joint, reading=readings.index(m.joint), coupled=True,
                            multiplier=float(1.0 if m.multiplier is None else m.multiplier),
                            mimic_offset=float(0.0 if m.offset is None else m.offset))
        elif joint.movable:
            joint = replace(joint, reading=readings.index(name))
        joints.append(joint)
    if not readings:
        raise InputError(source, f"no movable joint between '{base}' and " + ", ".join(f"'{tip}'" for tip in tips))
    return JointChain(tuple(joints), base, tuple(tips), tuple(tip_paths), tuple(readings), urdf=text,
                      sources=sources)


def robot_from_urdf(text: str, base: str, tip: str | Sequence[str], source: str = "<robot_description>",
                    slm: Slm | None = None, lasers: Sequence[Laser] = (), screen: Screen = Screen(),
                    name: str | None = None) -> Robot:
    """A Robot from URDF text (a file's or the /robot_description parameter's).

    Without lasers it is a robot for point / pose sensors (no SLM parameters);
    with them, ``slm`` places the laser module on the (first) tip link as in a
    robot file (conventions.md), and spots are predicted from the first tip.
    """
    tips = check_tips((tip,) if isinstance(tip, str) else tuple(tip), source)
    refuse_failed_urdf(text, source)
    if lasers and slm is None:
        raise InputError(source, "lasers need an slm placement")
    urdf = _parse(text, source)
    chain = chain_from_urdf(urdf, text, base, tips, source)
    robot_name = name or urdf.robot.name or "robot"
    return Robot(name=robot_name, joints=(), slm=slm, lasers=tuple(lasers), screen=screen, chain=chain)


def load_urdf_robot(path: str | Path, base: str, tip: str | Sequence[str]) -> Robot:
    return robot_from_urdf(urdf_text(path), base, tip, str(path))


def link_ends(text: str, listed: int = 12) -> str:
    """The root and leaf links of URDF text, for a message that asks for --base / --tip
    ("root link: world; leaf links: tool0, ..."); empty if the text is not XML."""
    from lxml import etree

    try:
        root = etree.fromstring(text.encode())
    except etree.XMLSyntaxError:
        return ""
    links = [link.get("name") for link in root.iter("link") if link.get("name")]
    parents, children = set(), set()
    for joint in root.iter("joint"):
        parent, child = joint.find("parent"), joint.find("child")
        if parent is not None and child is not None:  # a transmission's <joint> has neither
            parents.add(parent.get("link"))
            children.add(child.get("link"))
    roots = [link for link in links if link not in children]
    leaves = [link for link in links if link not in parents and link in children]
    if not roots:
        return ""

    def names(found: list[str]) -> str:
        more = f" and {len(found) - listed} more" if len(found) > listed else ""
        return ", ".join(found[:listed]) + more

    text = f"root link{'s' if len(roots) > 1 else ''}: {names(roots)}"
    return text + (f"; leaf links: {names(leaves)}" if leaves else "")


def check_tips(tips: Sequence[str], source: str) -> tuple[str, ...]:
    """The tip links: at least one, each once (a tip twice would be measured as two)."""
    if not tips or len(set(tips)) != len(tips):
        raise InputError(f"{source}: tip", f"expected a link name or a non-empty list of distinct link names, "
                                           f"got {', '.join(tips) or 'none'}")
    return tuple(tips)


def is_urdf(path: str | Path) -> bool:
    return Path(path).suffix.lower() in URDF_SUFFIXES


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
    with warnings.catch_warnings():  # at pitch +-pi/2 scipy sets yaw to 0 and roll to what composes the matrix
        warnings.filterwarnings("ignore", "Gimbal lock detected", UserWarning)
        rpy = Rotation.from_matrix(transform[:3, :3]).as_euler("xyz")
    return {"xyz": " ".join(repr(float(v)) for v in transform[:3, 3]),
            "rpy": " ".join(repr(float(v)) for v in rpy)}


def calibrated_urdf(robot: Robot) -> str:
    """The robot's URDF text with each movable joint's origin replaced by its
    calibrated one (its chain's values folded in: the text read back is the same
    robot with zero values)."""
    from lxml import etree

    root = etree.fromstring(robot.chain.urdf.encode(), etree.XMLParser(remove_blank_text=False))
    origins = calibrated_origins(robot)
    axes = {joint.name: joint.axis for joint in robot.chain.joints}
    for element in root.iter("joint"):
        name = element.get("name")
        if name not in origins or element.getparent() is not root:
            continue
        origin = element.find("origin")
        if origin is None:
            origin = etree.SubElement(element, "origin")
        for key, value in origin_attributes(origins[name]).items():
            origin.set(key, value)
        axis = element.find("axis")
        # The model moves along the unit axis, as urdfdom, KDL and MoveIt do; yourdfpy scales a prismatic
        # joint's motion by the axis's length: a unit axis written leaves no reader in doubt.
        if axis is not None and abs(np.linalg.norm(np.array(axis.get("xyz", "1 0 0").split(), float)) - 1.0) > 1e-12:
            axis.set("xyz", " ".join(repr(float(v)) for v in axes[name]))
    # the comments around <robot> (a generator's banner, a licence) are kept, but those a calibration
    # wrote there about its own fit (report.urdf_export): this file says its own
    around = [[etree.tostring(node, encoding="unicode", with_tail=False) for node in nodes
               if not (node.tag is etree.Comment and is_fit_mark(node.text or ""))]
              for nodes in (reversed(list(root.itersiblings(preceding=True))), root.itersiblings())]
    return "\n".join(around[0] + [etree.tostring(root, encoding="unicode", with_tail=False)] + around[1]) + "\n"

