"""The checks of a URDF's text before yourdfpy reads it (urdf.py): one line
naming the file and the link or joint, where yourdfpy would crash with a
message naming neither, trimesh would warn and go on with nan, the link
tree would hold a loop that a walk from a tip to the base never leaves, or
urdfdom (robot_state_publisher, RViz, MoveIt) would log an error for the
calibrated URDF, which carries the file's links verbatim (it keeps a link
whose inertial or shape it cannot read, without the link's other elements).

These hold for the whole file; what concerns the calibrated chain only (a
revolute joint's limits, a mimic's factor) is checked in urdf.py.
"""

from __future__ import annotations

import math

from laser_calib.io.errors import InputError

_TYPES = ("revolute", "continuous", "prismatic", "fixed", "floating", "planar")  # the URDF spec's
# A joint's elements besides parent and child (at most one each: yourdfpy reads the first only) ->
# their vector and number attributes, which yourdfpy reads as floats without naming the joint.
_JOINT_PARTS = {"origin": (("xyz", "rpy"), ()), "axis": (("xyz",), ()),
                "limit": ((), ("lower", "upper", "effort", "velocity")), "mimic": ((), ("multiplier", "offset")),
                "dynamics": ((), ("damping", "friction")), "calibration": ((), ("rising", "falling")),
                "safety_controller": ((), ("soft_lower_limit", "soft_upper_limit", "k_position", "k_velocity"))}
# The URDF spec's shapes -> their number attributes and how many numbers each holds.
_SHAPES = {"box": {"size": 3}, "cylinder": {"radius": 1, "length": 1}, "sphere": {"radius": 1}, "mesh": {"scale": 3}}
# An <inertial>'s elements -> their number attributes, each required by urdfdom.
_INERTIAL = {"mass": ("value",), "inertia": ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")}


def _named(elements: list, tag: str, source: str) -> dict:
    """Name -> element of the robot's <link> or <joint> elements, each named once."""
    out = {}
    for element in elements:
        name = element.get("name")
        if not name:
            raise InputError(f"{source}: line {element.sourceline}: {tag}", "missing attribute 'name'")
        if name in out:
            raise InputError(f"{source}: {tag} '{name}'", f"defined twice (lines {out[name].sourceline} and "
                                                          f"{element.sourceline})")
        out[name] = element
    return out


def _vector(where: str, element, key: str, count: int = 3, required: bool = False,
            bounds: tuple[float, float] = (-math.inf, math.inf)) -> None:
    """``count`` finite numbers within ``bounds``, if given (or ``required``): with
    fewer yourdfpy fails with an index or broadcast message, with nan / inf
    trimesh warns and the fit diverges, and urdfdom reads neither nan nor inf."""
    text = element.get(key)
    if text is None:
        if required:
            raise InputError(where, f"missing attribute '{key}'")
        return
    try:
        values = [float(v) for v in text.split()]
    except ValueError:
        values = []
    low, high = bounds
    if len(values) != count or not all(math.isfinite(v) and low <= v <= high for v in values):
        numbers = f"number{'s' if count > 1 else ''}"
        what = f"finite {numbers}" if bounds == (-math.inf, math.inf) else f"{numbers} in [{low:g}, {high:g}]"
        raise InputError(f"{where} {key}", f"expected {count} {what}, got {text!r}")


def _number(where: str, element, key: str) -> None:
    """A number, if given: yourdfpy's message for text names no joint, and nan is
    no value of anything (inf may be: a velocity, a continuous joint's bound)."""
    text = element.get(key)
    if text is None:
        return
    try:
        if not math.isnan(float(text)):
            return
    except ValueError:
        pass
    raise InputError(f"{where} {key}", f"expected a number, got {text!r}")


def _check_geometry(where: str, part) -> None:
    """The shape of a visual or collision element, as the URDF spec writes it:
    yourdfpy reads its numbers as floats, and what it cannot read it reports
    naming no link ('NoneType' object is not subscriptable, 'radius',
    could not convert string to float); a nan size it takes as one. The
    shape plays no part in the kinematics, but the calibrated URDF carries it
    verbatim to robot_state_publisher, RViz and MoveIt, whose parser (urdfdom)
    logs an error and drops the rest of the link."""
    geometry = part.find("geometry")
    shape = None if geometry is None else next((child for child in geometry if isinstance(child.tag, str)), None)
    if shape is None or shape.tag not in _SHAPES:
        got = "nothing" if shape is None else f"<{shape.tag}>"
        raise InputError(f"{where} geometry", f"expected a box, cylinder, sphere or mesh, got {got}")
    for key, count in _SHAPES[shape.tag].items():  # a mesh's scale is optional (1 1 1)
        _vector(f"{where} geometry {shape.tag}", shape, key, count, required=key != "scale")


def _check_inertial(where: str, part) -> None:
    """A <mass value> and an <inertia ixx ... izz>, each a finite number, as
    urdfdom requires (it takes a negative mass or moment, and so do we):
    yourdfpy's message for text in one names no link, and a nan or a missing
    one it takes without a word."""
    for tag, keys in _INERTIAL.items():
        found = part.find(tag)  # urdfdom reads the first
        if found is None:
            raise InputError(where, f"missing element <{tag}>")
        for key in keys:
            _vector(f"{where} {tag}", found, key, 1, required=True)


def _check_color(where: str, material) -> None:
    """A material's <color rgba>, if given: four numbers in [0, 1] (the URDF spec's;
    urdfdom logs an error for a component it cannot read or out of range, and
    takes a count other than four for black)."""
    color = material.find("color")  # urdfdom reads the first
    if color is not None:
        name = material.get("name")
        _vector(f"{where} '{name}' color" if name else f"{where} color", color, "rgba", 4, bounds=(0.0, 1.0))


def _check_link(name: str, element, source: str) -> None:
    """The origins of a link's inertial, visual and collision elements, the
    inertial's mass and inertia, the shapes of the visuals and collisions, and
    the colour of a visual's material (yourdfpy reads them all)."""
    for part in element:
        if part.tag not in ("inertial", "visual", "collision"):
            continue
        where = f"{source}: link '{name}': {part.tag}"
        origin = part.find("origin")
        if origin is not None:
            for key in ("xyz", "rpy"):
                _vector(f"{where} origin", origin, key)
        if part.tag == "inertial":
            _check_inertial(where, part)
        else:
            _check_geometry(where, part)
        material = part.find("material") if part.tag == "visual" else None
        if material is not None:
            _check_color(f"{where} material", material)


def _check_joint(name: str, element, links: dict, source: str) -> tuple[str, str]:
    """The parent and child link of a joint whose elements yourdfpy can read as written."""
    where = f"{source}: joint '{name}'"
    if element.get("type") not in _TYPES:
        raise InputError(f"{where}: type", f"expected one of {', '.join(_TYPES)}, got {element.get('type')!r}")
    ends = []
    for tag in ("parent", "child"):
        found = element.findall(tag)
        if len(found) != 1 or not found[0].get("link"):
            got = "one without link" if len(found) == 1 else len(found)
            raise InputError(f"{where}: {tag}", f"expected one <{tag} link=\"...\"/>, got {got}")
        if found[0].get("link") not in links:
            raise InputError(f"{where}: {tag}", f"no link '{found[0].get('link')}'")
        ends.append(found[0].get("link"))
    for tag, (vectors, numbers) in _JOINT_PARTS.items():
        found = element.findall(tag)
        if len(found) > 1:
            raise InputError(f"{where}: {tag}", f"{len(found)} <{tag}> elements (a joint has at most one)")
        for part in found:
            for key in vectors:
                _vector(f"{where}: {tag}", part, key)
            for key in numbers:
                _number(f"{where}: {tag}", part, key)
    return ends[0], ends[1]


def _check_loops(parent_of: dict[str, str], joint_of: dict[str, str], source: str) -> None:
    """Every walk up from a link ends at a root: a link that is its own ancestor
    would hang it. ``parent_of``, ``joint_of``: child link -> parent link, joint."""
    rooted: set[str] = set()
    for start in parent_of:
        walk: dict[str, int] = {}  # link -> its step in this walk
        link = start
        while link in parent_of and link not in rooted:
            if link in walk:
                loop = list(walk)[walk[link]:]
                raise InputError(f"{source}: joint '{joint_of[link]}'",
                                 f"kinematic loop (link '{link}' is its own ancestor through joints "
                                 f"{', '.join(joint_of[each] for each in loop)})")
            walk[link] = len(walk)
            link = parent_of[link]
        rooted.update(walk)


def check_tree(root, source: str) -> None:
    """``root``: the parsed <robot> element (lxml). One line naming the link or
    joint for what yourdfpy would crash on, read wrong without a word, or turn
    into a tree our walks never leave: names missing or twice, a joint's parent
    / child not one link, a link the child of two joints, a loop, a vector not
    of three finite numbers, a number that is none; and, for urdfdom, a link's
    inertial or a colour it cannot read, and a second root link."""
    if root.tag != "robot":
        raise InputError(source, f"expected a <robot> element, got <{root.tag}>")
    if root.get("name") is None:
        raise InputError(f"{source}: robot", "missing attribute 'name'")
    for material in root.findall("material"):
        _check_color(f"{source}: material", material)
    links = _named(root.findall("link"), "link", source)
    for name, element in links.items():
        _check_link(name, element, source)
    parent_of: dict[str, str] = {}
    joint_of: dict[str, str] = {}
    for name, element in _named(root.findall("joint"), "joint", source).items():
        parent, child = _check_joint(name, element, links, source)
        if child in joint_of:
            raise InputError(f"{source}: link '{child}'", f"child of two joints ('{joint_of[child]}' and "
                                                          f"'{name}'): a closed loop, which a URDF cannot describe")
        parent_of[child], joint_of[child] = parent, name
    _check_loops(parent_of, joint_of, source)
    roots = [link for link in links if link not in parent_of]
    if len(roots) > 1:  # kept in the calibrated URDF, which robot_state_publisher then could not load
        raise InputError(f"{source}: link '{roots[1]}'", f"a second root link beside '{roots[0]}' (no joint has it "
                                                         "as its child): urdfdom (robot_state_publisher, RViz, "
                                                         "MoveIt) refuses a URDF with two root links")
