"""Bad URDFs and URDF robot YAMLs (issue 9, section 3): one line on stderr
naming the file and the joint, link or key, exit status 2 -- never a hang, a
warning line, a traceback, a message blaming the samples, or exit 0 with a
robot the file did not describe.

Each case edits a small arm (three joints on the chain to ``tool``, a camera
mount and a fan off it) and runs ``calibrate-poses``: the robot is read before
the samples, so none are needed.
"""

import io
import signal
from contextlib import contextmanager
from pathlib import Path

import pytest
import yaml
import yourdfpy

from laser_calib.cli.main import main
from laser_calib.io.errors import InputError
from laser_calib.model.robot_file import dump_robot, robot_from_dict
from laser_calib.model.urdf import chain_from_urdf, robot_from_urdf
from laser_calib.sim.simulation import bundled_robot

DATA = Path(__file__).parent / "data"
UR10E = Path(__file__).resolve().parents[2] / "data" / "real" / "ur10e_mocap" / "ur10_robot.urdf"
ARM = """<?xml version="1.0"?>
<robot name="arm3">
  <link name="base_link"/><link name="l1"/><link name="l2"/><link name="tool"/><link name="cam"/><link name="fan"/>
  <joint name="j1" type="revolute"><parent link="base_link"/><child link="l1"/>
    <origin xyz="0 0 0.3" rpy="0 0 0"/><axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="9" velocity="1"/>
  </joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="0.4 0 0" rpy="1.5707963 0 0"/><axis xyz="0 0 1"/><limit lower="-2" upper="2" effort="9" velocity="1"/>
  </joint>
  <joint name="j3" type="prismatic"><parent link="l2"/><child link="tool"/>
    <origin xyz="0.3 0 0" rpy="0 0 0"/><axis xyz="1 0 0"/><limit lower="0" upper="0.2" effort="9" velocity="1"/>
  </joint>
  <joint name="camera_mount" type="fixed"><parent link="base_link"/><child link="cam"/><origin xyz="1 0 1"/></joint>
  <joint name="fan_spin" type="revolute"><parent link="cam"/><child link="fan"/><axis xyz="0 0 1"/></joint>
</robot>
"""
J2_LIMIT = '<limit lower="-2" upper="2" effort="9" velocity="1"/>'
INERTIA = {"ixx": "1", "ixy": "0", "ixz": "0", "iyy": "1", "iyz": "0", "izz": "1"}


def _inertial(link: str, mass: str = '<mass value="1"/>', **moments: str | None) -> tuple:
    """(text replaced, by) in ARM: ``link`` with an <inertial> of ``mass`` (its element's
    text) and an <inertia> whose ``moments`` replace INERTIA's (None: left out)."""
    inertia = " ".join(f'{key}="{value}"' for key, value in {**INERTIA, **moments}.items() if value is not None)
    return f'<link name="{link}"/>', f'<link name="{link}"><inertial>{mass}<inertia {inertia}/></inertial></link>'


def _colour(link: str, rgba: str) -> tuple:
    """(text replaced, by) in ARM: ``link`` with a box visual of material 'paint' of ``rgba``."""
    return f'<link name="{link}"/>', (f'<link name="{link}"><visual><geometry><box size="1 1 1"/></geometry>'
                                      f'<material name="paint"><color rgba="{rgba}"/></material></visual></link>')


BAD = {  # (text replaced, by) in ARM -> the one line
    "kinematic loop": (('<parent link="base_link"/><child link="l1"/>', '<parent link="tool"/><child link="l1"/>'),
                       "arm.urdf: joint 'j1': kinematic loop (link 'l1' is its own ancestor"),
    "nan in an origin": (('xyz="0.4 0 0"', 'xyz="nan 0 0"'),
                         "arm.urdf: joint 'j2': origin xyz: expected 3 finite numbers, got 'nan 0 0'"),
    "inf in an origin": (('rpy="1.5707963 0 0"', 'rpy="inf 0 0"'),
                         "joint 'j2': origin rpy: expected 3 finite numbers, got 'inf 0 0'"),
    "two numbers for rpy": (('rpy="1.5707963 0 0"', 'rpy="0 0"'),
                            "joint 'j2': origin rpy: expected 3 finite numbers, got '0 0'"),
    "two numbers for an axis": (('<axis xyz="0 0 1"/>' + J2_LIMIT, '<axis xyz="0 1"/>' + J2_LIMIT),
                                "joint 'j2': axis xyz: expected 3 finite numbers, got '0 1'"),
    "nan in a visual origin": (('<link name="l1"/>', '<link name="l1"><visual><origin xyz="0 0 nan"/>'
                                                     '<geometry><box size="1 1 1"/></geometry></visual></link>'),
                               "link 'l1': visual origin xyz: expected 3 finite numbers"),
    "nan in a box": (('<link name="fan"/>', '<link name="fan"><collision><geometry><box size="nan 1 1"/></geometry>'
                                            '</collision></link>'),
                     "arm.urdf: link 'fan': collision geometry box size: expected 3 finite numbers, got 'nan 1 1'"),
    "text for a radius": (('<link name="l2"/>', '<link name="l2"><visual><geometry><cylinder radius="abc" length="1"/>'
                                                '</geometry></visual></link>'),
                          "arm.urdf: link 'l2': visual geometry cylinder radius: expected 1 finite number, got 'abc'"),
    "a sphere without radius": (('<link name="l2"/>', '<link name="l2"><visual><geometry><sphere/></geometry></visual>'
                                                      '</link>'),
                                "arm.urdf: link 'l2': visual geometry sphere: missing attribute 'radius'"),
    "two numbers for a mesh scale": (('<link name="l2"/>', '<link name="l2"><visual><geometry><mesh filename="a.stl" '
                                                           'scale="1 1"/></geometry></visual></link>'),
                                     "link 'l2': visual geometry mesh scale: expected 3 finite numbers, got '1 1'"),
    "a visual without geometry": (('<link name="l2"/>', '<link name="l2"><visual><origin xyz="0 0 0"/></visual>'
                                                        '</link>'),
                                  "link 'l2': visual geometry: expected a box, cylinder, sphere or mesh, got nothing"),
    "nan mass": (_inertial("l1", mass='<mass value="nan"/>'),
                 "arm.urdf: link 'l1': inertial mass value: expected 1 finite number, got 'nan'"),
    "text for a mass": (_inertial("fan", mass='<mass value="abc"/>'),
                        "arm.urdf: link 'fan': inertial mass value: expected 1 finite number, got 'abc'"),
    "an inertial without mass": (_inertial("l2", mass=''), "arm.urdf: link 'l2': inertial: missing element <mass>"),
    "a mass without value": (_inertial("l2", mass='<mass/>'),
                             "arm.urdf: link 'l2': inertial mass: missing attribute 'value'"),
    "inf in an inertia": (_inertial("l1", ixx="inf"),
                          "arm.urdf: link 'l1': inertial inertia ixx: expected 1 finite number, got 'inf'"),
    "text for a product of inertia": (_inertial("l1", ixy="abc"),
                                      "link 'l1': inertial inertia ixy: expected 1 finite number, got 'abc'"),
    "an inertia without izz": (_inertial("l1", izz=None),
                               "arm.urdf: link 'l1': inertial inertia: missing attribute 'izz'"),
    "an inertial without inertia": (('<link name="l1"/>', '<link name="l1"><inertial><mass value="1"/></inertial>'
                                                          '</link>'),
                                    "arm.urdf: link 'l1': inertial: missing element <inertia>"),
    "a colour out of range": (_colour("l2", "255 0 0 1"), "arm.urdf: link 'l2': visual material 'paint' color rgba: "
                                                          "expected 4 numbers in [0, 1], got '255 0 0 1'"),
    "three numbers for a colour": (_colour("fan", "1 0 0"),
                                   "link 'fan': visual material 'paint' color rgba: expected 4 numbers in [0, 1]"),
    "nan in a colour": (_colour("l1", "nan 0 0 1"),
                        "link 'l1': visual material 'paint' color rgba: expected 4 numbers in [0, 1], got 'nan 0 0 1'"),
    "nan in a robot's material": (('<robot name="arm3">', '<robot name="arm3"><material name="red"><color '
                                                          'rgba="0 nan 0 1"/></material>'),
                                  "arm.urdf: material 'red' color rgba: expected 4 numbers in [0, 1], got '0 nan 0 1'"),
    "no parent": (('<parent link="l1"/>', ''), "joint 'j2': parent: expected one <parent link=\"...\"/>, got 0"),
    "no child": (('<child link="l2"/>', ''), "joint 'j2': child: expected one <child link=\"...\"/>, got 0"),
    "two parents": (('<parent link="l1"/>', '<parent link="l1"/><parent link="base_link"/>'),
                    "joint 'j2': parent: expected one <parent link=\"...\"/>, got 2"),
    "a child that is no link": (('<child link="l2"/>', '<child link="l9"/>'), "joint 'j2': child: no link 'l9'"),
    "no joint name": (('<joint name="j2" type="revolute">', '<joint type="revolute">'),
                      "arm.urdf: line 7: joint: missing attribute 'name'"),
    "no joint type": (('name="j2" type="revolute"', 'name="j2"'), "joint 'j2': type: expected one of revolute"),
    "a link twice": (('<link name="cam"/>', '<link name="cam"/><link name="l1"/>'),
                     "arm.urdf: link 'l1': defined twice (lines 3 and 3)"),
    "a joint name twice": (('name="camera_mount"', 'name="j2"'),
                           "arm.urdf: joint 'j2': defined twice (lines 7 and 13)"),
    "a second root": (('<link name="fan"/>', '<link name="fan"/><link name="orphan"/>'),
                      "arm.urdf: link 'orphan': a second root link beside 'base_link' (no joint has it as its child): "
                      "urdfdom (robot_state_publisher, RViz, MoveIt) refuses a URDF with two root links"),
    "a link the child of two joints": (('<child link="cam"/>', '<child link="l2"/>'),
                                       "arm.urdf: link 'l2': child of two joints ('j2' and 'camera_mount')"),
    "revolute without limit": ((J2_LIMIT, ''), "joint 'j2': limit: a revolute joint needs finite <limit lower="),
    "prismatic without limit": (('<limit lower="0" upper="0.2" effort="9" velocity="1"/>', ''),
                                "joint 'j3': limit: a prismatic joint needs finite <limit lower="),
    "limit without effort and velocity": ((J2_LIMIT, '<limit lower="-2" upper="2"/>'),
                                          "arm.urdf: joint 'j2': limit: missing attribute 'effort' and 'velocity': "
                                          "urdfdom (robot_state_publisher, RViz, MoveIt) refuses"),
    "limit without velocity": (('upper="3" effort="9" velocity="1"/>', 'upper="3" effort="9"/>'),
                               "joint 'j1': limit: missing attribute 'velocity'"),
    "limit without lower": (('lower="-2" upper="2"', 'upper="2"'), "joint 'j2': limit: a revolute joint needs"),
    "nan bound": (('lower="-2" upper="2"', 'lower="-2" upper="nan"'), "joint 'j2': limit upper: expected a number, "
                                                                      "got 'nan'"),
    "infinite bound on the chain": (('lower="-2" upper="2"', 'lower="-2" upper="inf"'),
                                    "joint 'j2': limit: a revolute joint needs finite <limit lower="),
    "revolute limits in degrees": (('lower="-2" upper="2"', 'lower="-30" upper="30"'),
                                   "arm.urdf: joint 'j2': limit lower: -30 rad is not a plausible angle: angles are "
                                   "in radians (this looks like degrees)"),
    "prismatic limit in centimetres": (('lower="0" upper="0.2"', 'lower="0" upper="50"'),
                                       "arm.urdf: joint 'j3': limit upper: 50 m is not a plausible prismatic limit "
                                       "(over 20 m): lengths are in metres (this looks like millimetres or "
                                       "centimetres)"),
    "infinite mimic multiplier": (('<limit lower="0" upper="0.2" effort="9" velocity="1"/>',
                                   '<limit lower="0" upper="0.2" effort="9" velocity="1"/>'
                                   '<mimic joint="j2" multiplier="inf"/>'),
                                  "joint 'j3': mimic: expected a finite multiplier and offset, got inf and 0.0"),
    "a tip twice": ((None, None), "arm.urdf: tip: expected a link name or a non-empty list of distinct link names"),
}


class _Hung(BaseException):
    """Not an Exception: the command line's catch-all must not turn it into exit 2."""


@contextmanager
def _within(seconds: float):
    """A hang (a walk up a looping tree) fails the test instead of the run."""
    def hung(*_):
        raise _Hung(f"still running after {seconds} s")

    previous = signal.signal(signal.SIGALRM, hung)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def _one_line(capsys, code: int, message: str) -> None:
    err = capsys.readouterr().err
    assert code == 2 and message in err, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err and "Warning" not in err, err


def _calibrate_poses(folder: Path, robot: Path, *base_tip: str) -> int:
    with _within(10):
        return main(["calibrate-poses", "--robot", str(robot), *base_tip, "--samples", str(folder / "none.csv"),
                     "--out", str(folder / "out")])


@pytest.mark.parametrize("case", BAD)
def test_bad_urdfs_are_one_line_naming_the_joint_or_link_and_exit_2(case, tmp_path, capsys):
    (old, new), message = BAD[case]
    assert old is None or ARM.count(old) == 1
    (tmp_path / "arm.urdf").write_text(ARM if old is None else ARM.replace(old, new))
    tips = ["tool", "tool"] if case == "a tip twice" else ["tool"]
    _one_line(capsys, _calibrate_poses(tmp_path, tmp_path / "arm.urdf", "--base", "base_link", "--tip", *tips),
              message)


def test_a_loop_in_the_ur10e_urdf_is_one_line(tmp_path, capsys):
    """The tester's edit: the shoulder hangs from the wrist."""
    if not UR10E.exists():
        pytest.skip(f"{UR10E} not available")
    text = UR10E.read_text().replace('<parent link="base_link_inertia"/>', '<parent link="wrist_3_link"/>', 1)
    (tmp_path / "ur10_robot.urdf").write_text(text)
    code = _calibrate_poses(tmp_path, tmp_path / "ur10_robot.urdf", "--base", "base_link", "--tip", "wrist_3_link")
    _one_line(capsys, code, "ur10_robot.urdf: joint 'shoulder_pan_joint': kinematic loop (link 'shoulder_link' is its "
                            "own ancestor through joints shoulder_pan_joint, wrist_3_joint")


def test_a_bad_shape_in_the_ur10e_urdf_names_the_link(tmp_path, capsys):
    """The tester's edit: a box of nan size for the upper arm's collision mesh."""
    if not UR10E.exists():
        pytest.skip(f"{UR10E} not available")
    mesh = '<mesh filename="package://ur_description/meshes/ur10e/collision/upperarm.stl"/>'
    (tmp_path / "ur10_robot.urdf").write_text(UR10E.read_text().replace(mesh, '<box size="nan 1 1"/>', 1))
    code = _calibrate_poses(tmp_path, tmp_path / "ur10_robot.urdf", "--base", "base_link", "--tip", "wrist_3_link")
    _one_line(capsys, code, "ur10_robot.urdf: link 'upper_arm_link': collision geometry box size: expected 3 finite "
                            "numbers, got 'nan 1 1'")


@pytest.mark.parametrize("old, new, message", [
    ('<mass value="12.93"/>', '<mass value="12,93"/>',
     "ur10_robot.urdf: link 'upper_arm_link': inertial mass value: expected 1 finite number, got '12,93'"),
    ('<color rgba="0.7 0.7 0.7 1.0"/>', '<color rgba="178 178 178 255"/>',
     "ur10_robot.urdf: link 'base_link_inertia': visual material 'LightGrey' color rgba: expected 4 numbers in "
     "[0, 1], got '178 178 178 255'")], ids=["decimal comma", "0-255 colour"])
def test_a_bad_mass_or_colour_in_the_ur10e_urdf_names_the_link(old, new, message, tmp_path, capsys):
    """A mass with a decimal comma (yourdfpy's line named no link) and a colour on the
    0-255 scale (yourdfpy took it): robot_state_publisher would log an error for each."""
    if not UR10E.exists():
        pytest.skip(f"{UR10E} not available")
    (tmp_path / "ur10_robot.urdf").write_text(UR10E.read_text().replace(old, new, 1))
    code = _calibrate_poses(tmp_path, tmp_path / "ur10_robot.urdf", "--base", "base_link", "--tip", "wrist_3_link")
    _one_line(capsys, code, message)


def test_shapes_as_the_spec_writes_them_load():
    """A comment before the shape, a mesh without scale: as robot_state_publisher reads them."""
    shapes = ('<link name="l2"><visual><geometry><!-- the casting --><mesh filename="package://arm/l2.stl"/>'
              '</geometry></visual><collision><geometry><cylinder radius="0.05" length="0.3"/></geometry>'
              '</collision></link>')
    assert robot_from_urdf(ARM.replace('<link name="l2"/>', shapes), "base_link", "tool").joint_names == \
        ("j1", "j2", "j3")


def test_inertials_and_colours_urdfdom_reads_load():
    """Not stricter than urdfdom (robot_state_publisher's parser): a negative mass or
    product of inertia, colours at 0 and 1, a material defined once at the top and
    named in a visual, a material with a texture and no colour."""
    text = ARM.replace('<robot name="arm3">', '<robot name="arm3"><material name="red"><color rgba="1 0 0 1"/>'
                                              '</material><material name="skin"><texture filename="a.png"/>'
                                              '</material>')
    old, new = _inertial("l1", mass='<mass value="-0.5"/>', ixy="-0.2")
    _, paint = _colour("l2", "0 0.5 1 0")
    visuals = '<visual><geometry><sphere radius="1"/></geometry><material name="{}"/></visual>'
    text = text.replace(old, new).replace('<link name="l2"/>', paint.replace(
        "</link>", visuals.format("red") + visuals.format("skin") + "</link>"))
    assert robot_from_urdf(text, "base_link", "tool").joint_names == ("j1", "j2", "j3")


def test_a_walk_up_a_looping_tree_ends_even_unchecked():
    """chain_from_urdf given a parsed URDF that never went through the checks."""
    text = ARM.replace('<parent link="base_link"/><child link="l1"/>', '<parent link="tool"/><child link="l1"/>')
    urdf = yourdfpy.URDF.load(io.BytesIO(text.encode()), build_scene_graph=False, load_meshes=False)
    with _within(10), pytest.raises(InputError, match="arm.urdf: kinematic loop"):
        chain_from_urdf(urdf, text, "base_link", ("tool",), "arm.urdf")


def test_a_joint_without_limits_off_the_chain_is_no_concern():
    """fan_spin (revolute, no <limit>: the spec's 0..0) moves no joint of base_link -> tool;
    on the chain to the fan it is refused."""
    assert robot_from_urdf(ARM, "base_link", "tool").joint_names == ("j1", "j2", "j3")
    with pytest.raises(InputError, match="joint 'fan_spin': limit: a revolute joint needs finite"):
        robot_from_urdf(ARM, "base_link", "fan")


@pytest.mark.parametrize("name", ["ARM.URDF", "arm.xml"])
def test_a_urdf_named_in_capitals_or_xml_is_read_as_a_urdf(name, tmp_path, capsys):
    """Not as a robot YAML (whose reader said --base / --tip apply to a URDF only): the samples are
    reached, and their absence is the one line."""
    (tmp_path / name).write_text(ARM)
    _one_line(capsys, _calibrate_poses(tmp_path, tmp_path / name, "--base", "base_link", "--tip", "tool"),
              "none.csv")


def test_a_urdf_not_in_utf8_is_said_so(tmp_path, capsys):
    (tmp_path / "arm.urdf").write_bytes(ARM.replace("arm3", "arm\xe9", 1).encode("latin-1"))
    _one_line(capsys, _calibrate_poses(tmp_path, tmp_path / "arm.urdf", "--base", "base_link", "--tip", "tool"),
              "arm.urdf: line 2: not UTF-8 text (byte 0xe9)")


def _urdf_robot_yaml(folder: Path, **keys) -> Path:
    """The paper's arm as a URDF robot YAML with lasers (the tester's file), ``keys`` replaced."""
    (folder / "arm7.urdf").write_text((DATA / "paper_arm_7dof.urdf").read_text())
    data = {"urdf": "arm7.urdf", "base": "link0", "tip": "link7_theta",
            "slm": {"a": 0.05, "d": 0.0, "alpha": 0.0, "theta": 3.1415926536, "beta": 0.0},
            "lasers": [{"gamma": -0.5235987756, "beta": 0.0}, {"gamma": 0.5235987756, "beta": 0.0}],
            "screen": {"half_y": 1.0, "half_z": 1.0}, **keys}
    (folder / "arm7.yaml").write_text(yaml.safe_dump(data))
    return folder / "arm7.yaml"


@pytest.mark.parametrize("tip", [[], ["link7_theta", "link7_theta"]])
def test_no_tip_or_a_tip_twice_in_a_robot_yaml_is_one_line(tip, tmp_path, capsys):
    path = _urdf_robot_yaml(tmp_path, tip=tip)
    code = main(["identify", "--robot", str(path), "--samples", str(tmp_path / "none.csv")])
    _one_line(capsys, code, "arm7.yaml: tip: expected a link name or a non-empty list of distinct link names")


def test_a_bad_frame_in_a_urdf_robot_yaml_names_the_file(tmp_path, capsys):
    path = _urdf_robot_yaml(tmp_path, frames={"sensor": {"x": float("nan")}})
    _one_line(capsys, _calibrate_poses(tmp_path, path), "arm7.yaml: frames.sensor.x: expected a finite number, got nan")


def test_a_bad_frame_in_a_dh_robot_yaml_names_the_file():
    data = yaml.safe_load(dump_robot(bundled_robot("paper-4dof")))
    data["frames"] = {"base": {"qw": 0.1}}
    with pytest.raises(InputError, match=r"^dh\.yaml: frames\.base: quaternion norm"):
        robot_from_dict(data, "dh.yaml")
