"""spot_detector behind a camera driver as most publish: best-effort images in the driver's
encoding, with CameraInfo."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

CLIENT = Path(__file__).with_name("camera_client.py")


def run_camera(ros, *args) -> dict:
    result = ros.run([sys.executable, str(CLIENT), *args], timeout=120)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_best_effort_camera_in_its_encoding(ros, tmp_path):
    ros.start("spot_detector", "-p", f"capture_dir:={tmp_path / 'captured'}", "-p", "capture_count:=2",
              "-p", "capture_period:=0.0")
    # one detector: it follows each frame's encoding; a best-effort driver and a reliable one
    for encoding, qos in (("rgb8", "sensor_data"), ("bayer_rggb8", "sensor_data"), ("bgr8", "reliable")):
        got = run_camera(ros, encoding, "0", "60", qos)
        assert got["frames"] >= 3, ros.log("spot_detector")
        spots = np.array(got["spots"])                       # (F,2,3): y, z, seen
        assert spots[:, :, 2].all()
        # the detector's accuracy on rendered frames is ~0.1 mm (bench/results/vision.md); 1 mm is far off
        assert np.abs(spots[:, :, :2] - np.array(got["true"])).max() < 1e-3
        # a reliable frame reaches both camera subscriptions: still one spot pair per frame
        assert len({tuple(s) for s in got["stamps"]}) == len(got["stamps"])
    assert sorted(p.name for p in (tmp_path / "captured").iterdir()) == ["frame_0000.png", "frame_0001.png"]


def test_best_effort_frames_of_4_mb_arrive(ros):
    """A driver's best-effort 1280x1024 rgb8 frames (3.9 MB) reach the detector: with Fast DDS's
    default 512 KB shared-memory segment about 3 of 4 were lost whole (the publisher's segment
    counts; config/fastdds_large_frames.xml, which scripts/env.sh gives every process)."""
    ros.start("spot_detector")
    got = run_camera(ros, "rgb8", "0", "60", "sensor_data", "12")
    assert got["published"] == 12
    # a frame may still be lost when the machine stalls for a whole period; 3 of 4 is the old loss
    assert got["frames"] >= 9, got["frames"]


def test_camera_info_of_another_size_refuses_frames_in_one_line(ros, tmp_path):
    """Every frame refused, the first too: a frame whose CameraInfo came second (the image first,
    or the info's subscription matched later) was used before the size was checked. Frames are
    still captured (capture_dir): they are for making the calibration this camera lacks (a camera
    of another size than the simulated one saved none, so its first screen calibration could not
    be made as docs/real-arm.md says)."""
    ros.start("spot_detector", "-p", f"capture_dir:={tmp_path / 'captured'}", "-p", "capture_count:=2",
              "-p", "capture_period:=0.0")
    got = run_camera(ros, "bgr8", "640", "8", "sensor_data", "0", "image_first")
    assert got["frames"] == 0
    log = ros.log("spot_detector")
    assert "CameraInfo says 640x1024, the calibration is for 1280x1024" in log and "Traceback" not in log
    assert sorted(p.name for p in (tmp_path / "captured").iterdir()) == ["frame_0000.png", "frame_0001.png"], log


def test_a_latched_camera_info_is_checked(ros):
    """A driver that latches its CameraInfo (sent once, transient local) before the detector
    started: the detector's transient-local subscription gets it, so its size is checked (here a
    wrong one: every frame refused). Without it the frames waited for an info that never came."""
    ros.start("spot_detector")
    got = run_camera(ros, "bgr8", "640", "8", "reliable", "3", "once_latched")
    assert got["frames"] == 0
    assert "CameraInfo says 640x1024, the calibration is for 1280x1024" in ros.log("spot_detector")


def test_a_camera_info_sent_once_and_lost_holds_back_a_few_frames_with_a_warning(ros):
    """A driver that sent its CameraInfo once, volatile, before anyone listened: the detector holds
    back INFO_WAIT_FRAMES frames for it, says so, then detects the rest. It waited for ever: every
    frame of the session was dropped without a word."""
    held_back = 5  # spot_detector.INFO_WAIT_FRAMES (its module needs the workspace's environment to import)
    # the driver first: its CameraInfo goes out before the detector exists. Started the other way round,
    # a discovery quicker than the driver's first publish delivered it (CI: 8 frames detected, none held)
    ros.start_command("camera", [sys.executable, str(CLIENT), "bgr8", "0", "20", "reliable", str(held_back + 3),
                                 "once"])
    ros.wait_log("camera", "camera info sent", 60)
    ros.start("spot_detector")
    assert ros.wait_exit("camera", 120) == 0, ros.log("camera")
    got = json.loads(ros.log("camera").strip().splitlines()[-1])
    assert got["frames"] == 3, ros.log("spot_detector")
    assert f"no CameraInfo on /camera/camera_info in {held_back} frames" in ros.log("spot_detector")


def test_a_refused_spot_is_a_warning_with_why(ros):
    """A camera noisier than spot_detector's noise parameters say (here: no speckle, a near
    noiseless sensor) has its clean spots refused as not one clean spot; the sequencer only sees
    'not seen', so the detector's WARN names the laser and why, which says what to set."""
    ros.start("spot_detector", "-p", "speckle_contrast:=0.0", "-p", "gain_e_per_dn:=1000000.0",
              "-p", "read_noise_dn:=0.01")
    # frames until 3 spot pairs came back: the first one can still be held back for its CameraInfo
    got = run_camera(ros, "bgr8", "0", "20", "reliable")
    assert got["frames"] >= 3 and not np.array(got["spots"])[:, :, 2].any(), got
    log = ros.log("spot_detector")
    assert "laser 1 refused: not one clean spot: its fit's chi^2 is" in log, log
    assert "laser 2 refused: not one clean spot" in log and "Traceback" not in log


def test_a_driver_distortion_other_than_the_calibrations_is_a_warning(ros):
    """spot_detector compared the driver's K with its calibration's, never D: a lens model that moves the
    image's edge by 20 px (a driver saying 'no distortion' of a k1 = -0.12 lens) passed unsaid."""
    ros.start("spot_detector")
    got = run_camera(ros, "bgr8", "0", "20", "reliable", "3", "zero_distortion")
    assert got["frames"] == 3
    log = ros.log("spot_detector")
    assert "the driver's CameraInfo distortion differs from the calibration file's by up to" in log, log


def test_frames_that_repeat_a_stamp_are_dropped_with_a_warning(ros):
    """A frame with the stamp of an earlier one was taken for that frame through the detector's other
    subscription and dropped without a word: a camera whose clock repeats stamps lost half its frames
    unsaid. Frames with the same stamp and other pixels are now said to be dropped (a spot is matched
    to the joint readings by its stamp); the same frame twice is still used once."""
    ros.start("spot_detector")
    got = run_camera(ros, "bgr8", "0", "20", "reliable", "6", "repeat_stamp")
    assert got["frames"] == 3 and len({tuple(s) for s in got["stamps"]}) == 3, got
    log = ros.log("spot_detector")
    assert "frames with the stamp of an earlier frame and other pixels dropped" in log, log


def test_sequencer_records_a_best_effort_camera(ros, tmp_path):
    """The bag holds camera_info (and the images, record_images) of a best-effort driver, whose
    frames a reliable subscription never matched (none were recorded), and each frame of a
    reliable one (camera_sim) once."""
    from laser_calib.io import bag
    from laser_calib.io.bag import bag_topics
    from ros_harness import ROBOT
    out = tmp_path / "session"
    ros.start("sequencer", "-p", f"robot:={ROBOT}", "-p", f"output_dir:={out}", "-p", "record_images:=true")
    for qos in ("sensor_data", "reliable"):
        assert run_camera(ros, "bgr8", "0", "30", qos, "3")["published"] == 3
    # a driver that latched its CameraInfo once, before it was listened to (told apart by its width)
    run_camera(ros, "bgr8", "640", "30", "reliable", "1", "once_latched")
    assert ros.stop("sequencer") == 0, ros.log("sequencer")
    topics = bag_topics(out / "bag")
    # the 3 reliable ones and the latched one, once each, and the best-effort ones, of which one may be
    # lost on a loaded machine (seen with two other jobs on the 2 cores, and that is best effort's contract)
    assert 5 <= topics["/camera/camera_info"][1] <= 7, topics
    assert 5 <= topics["/camera/image_raw"][1] <= 7, topics  # a best-effort 4 MB frame may be lost
    typestore = bag.typestore()
    widths = [typestore.deserialize_cdr(data, kind).width
              for _, kind, _, data in bag.read_messages(out / "bag", ["/camera/camera_info"])]
    assert widths.count(640) == 1, widths


HARDWARE_REMAPS = """import json, sys
from laser_calib_nodes.graph import HARDWARE_ARGS, hardware_nodes, share
values = {name: default for name, (default, _) in HARDWARE_ARGS.items()}
values.update(output_dir=sys.argv[1], robot=sys.argv[2], calibration=sys.argv[3], image="/my_camera/image_raw",
              arm_params=share("config", "dynamixel_arm.yaml"))
print(json.dumps([spec.remaps for spec in hardware_nodes(values) if spec.executable == "spot_detector"][0]))"""


def test_hardware_launch_takes_the_cameras_info_beside_its_image(ros, tmp_path):
    """hardware.launch.py image:=/my_camera/image_raw remapped the image alone: the driver's
    CameraInfo (/my_camera/camera_info) never reached spot_detector, whose check of the camera's
    size and intrinsics against the screen calibration then never ran, without a word. A driver
    whose CameraInfo says another size has its frames refused, as with the topics remapped by hand,
    the first too: spot_detector held frames back for a CameraInfo only when the unremapped
    camera/camera_info had a publisher (rclpy's count_publishers does not remap), so the first
    frame of a remapped driver was detected unchecked."""
    import json
    from laser_calib.vision.camera import default_camera, save_calibration
    from ros_harness import ROBOT
    save_calibration(default_camera().ideal_calibration(), tmp_path / "screen.yaml")
    out = ros.run([sys.executable, "-c", HARDWARE_REMAPS, str(tmp_path / "out"), str(ROBOT),
                   str(tmp_path / "screen.yaml")])
    assert out.returncode == 0, out
    remaps = json.loads(out.stdout)
    assert ["camera/camera_info", "/my_camera/camera_info"] in remaps, remaps
    ros.start("spot_detector", *[arg for old, new in remaps for arg in ("-r", f"{old}:={new}")])
    got = run_camera(ros, "bgr8", "640", "8", "sensor_data", "0", "image_first", "--ros-args",
                     "-r", "camera/image_raw:=/my_camera/image_raw", "-r", "camera/camera_info:=/my_camera/camera_info")
    assert got["frames"] == 0, ros.log("spot_detector")
    assert "CameraInfo says 640x1024, the calibration is for 1280x1024" in ros.log("spot_detector")
