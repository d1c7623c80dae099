"""Camera driver images to the detector's bgr8 (ROS-free): the sensor_msgs/Image
encodings drivers publish, decoded with OpenCV.

- bgr8, rgb8: colour as it is (channel order swapped for rgb8);
- bayer_rggb8, bayer_bggr8, bayer_gbrg8, bayer_grbg8: the raw mosaic, demosaiced
  as the simulated camera is (bilinear); the detector then fits only the
  photosites of each laser's colour in that pattern (``bayer_pattern``);
- yuv422 (UYVY, ROS's name) and yuv422_yuy2 (YUYV): BT.601 video YUV 4:2:2; the
  chroma is shared by two pixels, so every pixel counts as measured (no pattern);
- mono8: a mono camera cannot tell the red laser from the green one. Accepted only
  when the driver publishes a colour sensor's raw mosaic as mono8 (several do):
  ``mono_pattern`` names that mosaic.
Rows may be padded (step > width * bytes per pixel), as drivers are allowed to.
"""

from __future__ import annotations

import cv2
import numpy as np

BAYER = {"bayer_rggb8": "RGGB", "bayer_bggr8": "BGGR", "bayer_gbrg8": "GBRG", "bayer_grbg8": "GRBG"}
# OpenCV names a Bayer layout by the 2 x 2 cell starting at the second row and column.
_DEMOSAIC = {"RGGB": cv2.COLOR_BayerBG2BGR, "BGGR": cv2.COLOR_BayerRG2BGR, "GBRG": cv2.COLOR_BayerGR2BGR,
             "GRBG": cv2.COLOR_BayerGB2BGR}
_CHANNELS = {"bgr8": 3, "rgb8": 3, "mono8": 1, "yuv422": 2, "yuv422_yuy2": 2, **{name: 1 for name in BAYER}}
ENCODINGS = tuple(_CHANNELS)


def pattern_of(encoding: str, mono_pattern: str | None) -> str | None:
    """The Bayer pattern of the photosites behind an image of this encoding, when there is one
    to follow (raw mosaics); None: the detector's own setting applies."""
    if encoding in BAYER:
        return BAYER[encoding]
    return mono_pattern if encoding == "mono8" else None


def to_bgr8(data: bytes, width: int, height: int, step: int, encoding: str,
            mono_pattern: str | None = None) -> np.ndarray:
    """bgr8 (H, W, 3) uint8 of an image message's fields; ValueError in one line."""
    if encoding not in _CHANNELS:
        raise ValueError(f"encoding {encoding!r} not supported (supported: {', '.join(ENCODINGS)})")
    row_bytes = width * _CHANNELS[encoding]
    if width <= 0 or height <= 0 or step < row_bytes or len(data) < step * height:
        raise ValueError(f"{encoding} {width}x{height}: step {step}, {len(data)} bytes do not hold the image")
    rows = np.frombuffer(data, dtype=np.uint8, count=step * height).reshape(height, step)[:, :row_bytes]
    if encoding == "bgr8":
        return np.ascontiguousarray(rows.reshape(height, width, 3))
    if encoding == "rgb8":
        return cv2.cvtColor(np.ascontiguousarray(rows.reshape(height, width, 3)), cv2.COLOR_RGB2BGR)
    if encoding in ("yuv422", "yuv422_yuy2"):
        if width % 2:
            raise ValueError(f"{encoding}: width {width} is odd (4:2:2 pairs pixels)")
        code = cv2.COLOR_YUV2BGR_UYVY if encoding == "yuv422" else cv2.COLOR_YUV2BGR_YUY2
        return cv2.cvtColor(np.ascontiguousarray(rows.reshape(height, width, 2)), code)
    pattern = pattern_of(encoding, mono_pattern)
    if pattern is None:
        raise ValueError("mono8: a mono image cannot tell the two lasers apart by colour; if the driver "
                         "publishes a colour sensor's raw mosaic as mono8, set mono_pattern (e.g. RGGB)")
    if pattern not in _DEMOSAIC:
        raise ValueError(f"Bayer pattern {pattern!r}: expected one of {', '.join(_DEMOSAIC)}")
    return cv2.cvtColor(np.ascontiguousarray(rows), _DEMOSAIC[pattern])
