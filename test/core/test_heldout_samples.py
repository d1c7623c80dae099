"""One samples type for every sensor: spot, point and pose are measurement kinds;
both CSV formats are written byte for byte as before the unification."""

import numpy as np
import pytest

from laser_calib.io.samples import Samples, format_samples, parse_samples
from laser_calib.io.sensor_samples import format_sensor_samples, parse_sensor_samples

Q = np.array([[0.1, -0.25], [0.3, 1 / 3]])
POSE, STAMP = np.array([0, 3]), np.array([0.5, 1.25])
# The texts main's Samples / SensorSamples wrote for these rows (before the unification).
SPOT_TEXT = ("pose,stamp,q1,q2,l1_y,l1_z,l2_y,l2_z,temperature_c\n0,0.5,0.1,-0.25,0.01,-0.02,,,20.5\n"
             "3,1.25,0.3,0.3333333333333333,0.03333333333333333,0.2,0.3,-0.4,21.0\n")
POSE_TEXT = ("pose,stamp,q1,q2,x,y,z,qw,qx,qy,qz,t\n0,0.5,0.1,-0.25,1.5,0.2,-0.1,1.0,0.0,0.0,0.0,1.0\n"
             "3,1.25,0.3,0.3333333333333333,,,,,,,,2.0\n")
POINT_TEXT = "pose,stamp,q1,q2,x,y,z\n0,0.5,0.1,-0.25,1.5,0.2,-0.1\n3,1.25,0.3,0.3333333333333333,,,\n"


def spot_samples() -> Samples:
    spots = np.array([[[0.01, -0.02], [np.nan, np.nan]], [[0.1 / 3, 0.2], [0.3, -0.4]]])
    return Samples(POSE, STAMP, Q, spots, {"temperature_c": np.array([20.5, 21.0])})


def pose_samples() -> Samples:
    position = np.array([[1.5, 0.2, -0.1], [np.nan] * 3])
    quaternion = np.array([[1.0, 0, 0, 0], [np.nan] * 4])
    return Samples(POSE, STAMP, Q, extra={"t": np.array([1.0, 2.0])}, position=position, quaternion=quaternion)


def test_each_kind_is_written_as_before_and_reads_back():
    spot, pose = spot_samples(), pose_samples()
    point = Samples(POSE, STAMP, Q, position=pose.position)
    assert format_samples(spot) == SPOT_TEXT
    assert format_sensor_samples(pose) == POSE_TEXT
    assert format_sensor_samples(point) == POINT_TEXT
    assert [s.kind for s in (spot, point, pose)] == ["spot", "point", "pose"]
    back = parse_samples(SPOT_TEXT)
    assert back.kind == "spot" and np.array_equal(back.spots, spot.spots, equal_nan=True)
    assert parse_sensor_samples(POSE_TEXT).kind == "pose" and parse_sensor_samples(POINT_TEXT).kind == "point"
    assert format_sensor_samples(parse_sensor_samples(POSE_TEXT)) == POSE_TEXT


def test_seen_and_subset_follow_the_kind():
    spot, pose = spot_samples(), pose_samples()
    assert spot.seen.tolist() == [[True, False], [True, True]]
    assert pose.seen.tolist() == [True, False]
    part = pose.subset(np.array([1]))
    assert part.kind == "pose" and part.pose.tolist() == [3] and part.quaternion.shape == (1, 4)
    assert part.extra["t"].tolist() == [2.0] and part.spots is None
    assert spot.subset(np.array([True, False])).spots.shape == (1, 2, 2)


def test_a_mixed_up_construction_fails_at_once():
    pose = pose_samples()
    with pytest.raises(ValueError, match="exactly one"):
        Samples(POSE, STAMP, Q)
    with pytest.raises(ValueError, match="exactly one"):
        Samples(POSE, STAMP, Q, spot_samples().spots, position=pose.position)
    with pytest.raises(ValueError, match="spots of 2 poses"):
        Samples(POSE, STAMP, Q, pose.position)                  # positions passed where spots go
    with pytest.raises(ValueError, match="needs a position"):
        Samples(POSE, STAMP, Q, spot_samples().spots, quaternion=pose.quaternion)
    with pytest.raises(ValueError, match="extra"):
        Samples(POSE, STAMP, Q, spot_samples().spots, pose.quaternion)
    with pytest.raises(ValueError, match="point or pose"):
        format_sensor_samples(spot_samples())
    with pytest.raises(ValueError, match="spot"):
        format_samples(pose)
