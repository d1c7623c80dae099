"""Synthetic camera frames of the screen: laser spots, fiducials, calibration board.

Images are bgr8 (H, W, 3) uint8, the sensor_msgs/Image encoding 'bgr8'. The
camera is a colour camera with an RGGB Bayer mosaic (demosaiced by OpenCV), so
the two lasers are told apart by colour, as with a real SLM built from two
different diodes: laser 1 is red (~650 nm), laser 2 green (~520 nm).

What a frame contains, and why:

* geometry by projection: every pixel is traced back through the lens
  distortion to the plane it sees (screen, wall, board), so perspective and
  distortion are exact, not approximated;
* the screen's albedo: a white board with ArUco fiducials on its border
  (ScreenLayout), a darker wall beyond, sampled 3 x 3 per pixel;
* ambient light: warm white, a linear gradient of random direction per frame,
  and cos^4 vignetting;
* each laser spot: a Gaussian of sigma ``spot_sigma_m`` on the screen (the
  paper's ~4 mm diffraction length taken as 2 sigma), integrated over each
  pixel (5 x 5 samples), blurred by the lens PSF, multiplied by speckle; given
  the beam's direction, the footprint of a collimated beam: stretched by
  1 / cos i along the plane of incidence (i the angle to the screen's normal),
  its peak lowered by cos i (the same power on a larger area);
* speckle: an independent Gamma-distributed factor per photosite, of mean 1
  and standard deviation ``speckle_contrast`` (the pixel-integrated intensity
  of a speckle pattern with 1/contrast^2 grains per pixel). The default 0.1
  assumes many grains per pixel: a low-coherence multimode diode, a
  volume-scattering screen, a fast lens. Speckle limits the spot accuracy
  (see bench/vision_bench.py, which sweeps it);
* the sensor: Bayer colour filters with crosstalk, shot noise (Gaussian
  approximation of Poisson), read noise, saturation at full well = 255 DN.

Not modelled: the arm occluding the screen, blooming, motion blur; spot
elongation when the beams are not given (the simulated session's camera_sim is
given spots, not beams).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from laser_calib.vision.camera import CameraModel
from laser_calib.vision.screen_calibration import CharucoSpec, ScreenLayout

ENCODING = "bgr8"

# Response of the B, G, R channels (Bayer filters plus crosstalk) to each light.
AMBIENT_BGR = np.array([0.80, 1.00, 0.95])          # warm white room light
LASER_BGR = np.array([[0.01, 0.06, 1.00],           # laser 1: red
                      [0.10, 1.00, 0.12]])          # laser 2: green

SCREEN_ALBEDO = 0.85   # matte white
INK_ALBEDO = 0.05      # black print of markers and boards
WALL_ALBEDO = 0.3

_TEXEL = 0.002         # screen texture resolution, m; a marker cell is 10 texels
_SUPERSAMPLE = 3       # albedo samples per pixel and axis
_SPOT_SUPERSAMPLE = 5  # laser samples per pixel and axis


@dataclass(frozen=True)
class RenderOptions:
    """How the simulated camera sees the scene. DN: digital number, 0..255.

    spot_sigma_m: Gaussian sigma of each laser spot on the screen, m.
    psf_sigma_px: lens blur (Gaussian sigma), pixels.
    laser_radiance_dn: peak radiance of each laser's spot, as the DN it would
        give in its own colour channel on a white (albedo 1) surface with no
        blur; blur spreads it over ~10 px, so the default 600 gives an image
        peak of ~190 DN at the image centre, 110-150 DN in the screen's corners.
    speckle_contrast: standard deviation of the multiplicative speckle.
    ambient_dn: room light on an albedo-1 surface at the image centre, green
        DN (a dimmed room; the white screen shows ~42 DN).
    ambient_gradient: relative change of the ambient light from one side of
        the image to the other (in a random direction each frame).
    full_well_e: electrons at 255 DN; sets the shot noise.
    read_noise_e: read noise, electrons rms.
    """

    spot_sigma_m: float = 0.002
    psf_sigma_px: float = 1.0
    laser_radiance_dn: tuple[float, float] = (600.0, 600.0)
    speckle_contrast: float = 0.1
    ambient_dn: float = 50.0
    ambient_gradient: float = 0.5
    full_well_e: float = 10000.0
    read_noise_e: float = 10.0


@lru_cache(maxsize=4)
def _normalised_rays(camera: CameraModel) -> np.ndarray:
    """(H, W, 2): undistorted normalised image coordinates (x/z, y/z) of every pixel centre."""
    u, v = np.meshgrid(np.arange(camera.width, dtype=np.float64), np.arange(camera.height, dtype=np.float64))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1)
    return _undistort(camera, pixels).reshape(camera.height, camera.width, 2)


def _undistort(camera: CameraModel, pixels: np.ndarray) -> np.ndarray:
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    return cv2.undistortPoints(pixels.reshape(-1, 1, 2), camera.K, camera.dist, criteria=criteria).reshape(-1, 2)


def _rays_to_screen(camera: CameraModel, rays: np.ndarray) -> np.ndarray:
    """Screen (y, z) (..., 2) where normalised rays (..., 2) meet the plane x = 0."""
    rotation = camera.rotation
    direction = rays @ rotation[:2, :] + rotation[2, :]  # R^T (x, y, 1), in frame {0}
    centre = camera.position
    scale = -centre[0] / direction[..., 0]
    return centre[1:] + scale[..., None] * direction[..., 1:]


def _rays_to_board(rays: np.ndarray, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """Board (x, y) (..., 2) where normalised rays meet a board at pose (rvec, tvec) in the camera."""
    rotation = cv2.Rodrigues(np.asarray(rvec, float))[0]
    tvec = np.asarray(tvec, float).ravel()
    normal = rotation[:, 2]
    depth = (normal @ tvec) / (rays @ normal[:2] + normal[2])
    points = np.concatenate([rays, np.ones(rays.shape[:-1] + (1,))], axis=-1) * depth[..., None] - tvec
    xy = points @ rotation[:, :2]
    xy[depth <= 0] = -1e6  # the plane behind the camera is not seen
    return xy


def _sample(texture: np.ndarray, col: np.ndarray, row: np.ndarray, outside: float | tuple[float, ...]
            ) -> np.ndarray:
    """Pixel-area average (H, W[, C]) of ``texture`` at texel coordinates (col, row) (H, W) of the pixel centres.

    Sub-pixel positions follow the local Jacobian of the mapping, which is
    exact to first order in the 1/3 px offsets.
    """
    col_u, col_v = np.gradient(col, axis=1), np.gradient(col, axis=0)
    row_u, row_v = np.gradient(row, axis=1), np.gradient(row, axis=0)
    offsets = (np.arange(_SUPERSAMPLE) + 0.5) / _SUPERSAMPLE - 0.5
    # Only the pixels whose samples can reach the texture are remapped (a board fills a third of a
    # view; its nine remaps over the whole image were most of a render's time): every other pixel's
    # samples all read the border value, summed here as the remaps' would be.
    total = np.zeros(col.shape + texture.shape[2:], np.float32)
    for _ in range(_SUPERSAMPLE ** 2):
        total += np.asarray(outside, np.float32)
    reach = offsets.max() * (np.abs(col_u) + np.abs(col_v) + np.abs(row_u) + np.abs(row_v)) + 1.0  # texels
    texels_rows, texels_cols = texture.shape[:2]
    seen = ((col > -1.0 - reach) & (col < texels_cols + reach) & (row > -1.0 - reach) & (row < texels_rows + reach))
    rows, cols = np.flatnonzero(seen.any(axis=1)), np.flatnonzero(seen.any(axis=0))
    if rows.size:
        window = np.s_[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
        part = np.zeros(total[window].shape, np.float32)
        for du in offsets:
            for dv in offsets:
                map_c = (col[window] + du * col_u[window] + dv * col_v[window]).astype(np.float32)
                map_r = (row[window] + du * row_u[window] + dv * row_v[window]).astype(np.float32)
                part += cv2.remap(texture, map_c, map_r, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                                  borderValue=outside)
        total[window] = part
    return total / _SUPERSAMPLE ** 2


@lru_cache(maxsize=2)
def _screen_texture(layout: ScreenLayout) -> tuple[np.ndarray, float]:
    """Albedo of the screen plane, float32 (N, N), and its half extent in m.

    Texel (col, row) has its centre at y = extent - (col + 0.5) texel,
    z = extent - (row + 0.5) texel: the screen as seen from the front.
    """
    extent = layout.border + 0.1
    n = int(round(2 * extent / _TEXEL))
    texture = np.full((n, n), WALL_ALBEDO, np.float32)
    board = int(round((extent - layout.border) / _TEXEL))
    texture[board:n - board, board:n - board] = SCREEN_ALBEDO
    dictionary = cv2.aruco.getPredefinedDictionary(layout.dictionary)
    side = int(round(layout.marker_side / _TEXEL))
    for marker_id, (y, z) in zip(layout.marker_ids, layout.marker_centres):
        bits = cv2.aruco.generateImageMarker(dictionary, marker_id, side) > 127
        col = int(round((extent - y - 0.5 * layout.marker_side) / _TEXEL))
        row = int(round((extent - z - 0.5 * layout.marker_side) / _TEXEL))
        texture[row:row + side, col:col + side] = np.where(bits, SCREEN_ALBEDO, INK_ALBEDO)
    return texture, extent


@lru_cache(maxsize=4)
def _screen_maps(camera: CameraModel, layout: ScreenLayout) -> tuple[np.ndarray, np.ndarray]:
    """(albedo, vignetting), float32 (H, W), of the camera's view of the screen plane."""
    rays = _normalised_rays(camera)
    yz = _rays_to_screen(camera, rays)
    texture, extent = _screen_texture(layout)
    albedo = _sample(texture, (extent - yz[..., 0]) / _TEXEL - 0.5, (extent - yz[..., 1]) / _TEXEL - 0.5,
                     WALL_ALBEDO)
    vignetting = (1.0 + np.sum(rays ** 2, axis=-1)) ** -2.0  # cos^4 of the off-axis angle
    return albedo, vignetting.astype(np.float32)


@lru_cache(maxsize=2)
def _bayer_sites(height: int, width: int) -> np.ndarray:
    """(H, W) channel index (0 B, 1 G, 2 R) of each photosite of an RGGB mosaic."""
    sites = np.ones((height, width), np.intp)
    sites[0::2, 0::2] = 2
    sites[1::2, 1::2] = 0
    return sites


@lru_cache(maxsize=2)
def _ambient_response(height: int, width: int) -> np.ndarray:
    """(H, W) float32, read-only (cached): each photosite's response to the room light (AMBIENT_BGR in its colour)."""
    response = AMBIENT_BGR.astype(np.float32)[_bayer_sites(height, width)]
    response.setflags(write=False)
    return response


def _ambient(camera: CameraModel, rng: np.random.Generator, options: RenderOptions) -> np.ndarray:
    """Room light (H, W) float32 in DN on an albedo-1 surface, before vignetting."""
    angle = rng.uniform(0.0, 2.0 * np.pi)
    u = np.linspace(-0.5, 0.5, camera.width, dtype=np.float32)
    v = np.linspace(-0.5, 0.5, camera.height, dtype=np.float32)
    ramp = float(np.cos(angle)) * u[None, :] + float(np.sin(angle)) * v[:, None]  # float32, as u and v
    return options.ambient_dn * (1.0 + options.ambient_gradient * ramp)


def _footprint(beam: np.ndarray | None) -> tuple[float, np.ndarray]:
    """(cos i, t (2,)) of a beam (3,) in frame {0}: i its angle to the screen's normal, t the unit (y, z)
    direction of its plane of incidence; (1, 0) for None."""
    beam = np.array([1.0, 0.0, 0.0]) if beam is None else np.asarray(beam, float) / np.linalg.norm(beam)
    along = np.hypot(beam[1], beam[2])
    return abs(float(beam[0])), (beam[1:] / along if along > 0 else np.zeros(2))


def _spot(camera: CameraModel, layout: ScreenLayout, spot_yz: np.ndarray, radiance: float,
          rng: np.random.Generator, options: RenderOptions, beam: np.ndarray | None = None
          ) -> tuple[int, int, np.ndarray] | None:
    """One laser spot as (row0, col0, patch) with patch float32 DN, or None if out of view; beam (3,):
    the beam's direction in frame {0}, None for a round spot."""
    cos_i, incidence = _footprint(beam)
    centre, step = camera.project(np.array([spot_yz, spot_yz + [options.spot_sigma_m / cos_i, 0.0]]))
    sigma_px = np.hypot(np.linalg.norm(step - centre), options.psf_sigma_px)
    half = int(np.ceil(5.0 * sigma_px)) + 2
    col0, row0 = int(round(centre[0])) - half, int(round(centre[1])) - half
    size = 2 * half + 1
    if col0 + size <= 0 or row0 + size <= 0 or col0 >= camera.width or row0 >= camera.height:
        return None
    offsets = (np.arange(_SPOT_SUPERSAMPLE) + 0.5) / _SPOT_SUPERSAMPLE - 0.5
    grid = np.arange(size)[:, None] + offsets[None, :]
    u, v = np.meshgrid(col0 + grid.ravel(), row0 + grid.ravel())
    yz = _rays_to_screen(camera, _undistort(camera, np.stack([u.ravel(), v.ravel()], axis=1)))
    texture, extent = _screen_texture(layout)
    n = size * _SPOT_SUPERSAMPLE  # maps of n x n, not n^2 x 1: remap takes fewer than 32767 rows
    albedo = cv2.remap(texture, ((extent - yz[:, 0]) / _TEXEL - 0.5).astype(np.float32).reshape(n, n),
                       ((extent - yz[:, 1]) / _TEXEL - 0.5).astype(np.float32).reshape(n, n), cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_CONSTANT, borderValue=WALL_ALBEDO).ravel()
    # r^T C^-1 r, C = s^2 (I + (1 / cos^2 i - 1) t t^T): C^-1 = (I - (1 - cos^2 i) t t^T) / s^2
    offset = yz - spot_yz
    r2 = (np.sum(offset ** 2, axis=1) - (1.0 - cos_i ** 2) * (offset @ incidence) ** 2) / options.spot_sigma_m ** 2
    samples = (radiance * cos_i * albedo * np.exp(-0.5 * r2)).reshape(size, _SPOT_SUPERSAMPLE, size,
                                                                      _SPOT_SUPERSAMPLE)
    patch = samples.mean(axis=(1, 3)).astype(np.float32)
    patch = cv2.GaussianBlur(patch, (0, 0), options.psf_sigma_px, borderType=cv2.BORDER_CONSTANT)
    if options.speckle_contrast > 0.0:
        shape = 1.0 / options.speckle_contrast ** 2
        patch *= rng.gamma(shape, 1.0 / shape, patch.shape).astype(np.float32)
    return row0, col0, patch


def _expose(scene: np.ndarray, rng: np.random.Generator, options: RenderOptions) -> np.ndarray:
    """Noise, saturate, quantise and demosaic the photosite signal (H, W) DN into bgr8 (H, W, 3)."""
    gain = options.full_well_e / 255.0  # electrons per DN
    # In place, in the order of sqrt(max(scene, 0) / gain + (read / gain)^2) * N(0, 1) + scene: a frame
    # (1.3 Mpx) every 0.1 s per simulated camera, most of a simulated session's CPU.
    sigma = np.maximum(scene, 0.0)
    sigma /= gain
    sigma += (options.read_noise_e / gain) ** 2
    raw = rng.standard_normal(scene.shape, dtype=np.float32).astype(scene.dtype, copy=False)  # in its precision
    raw *= np.sqrt(sigma, out=sigma)
    raw += scene
    raw = np.clip(np.rint(raw, out=raw), 0, 255, out=raw).astype(np.uint8)
    return cv2.cvtColor(raw, cv2.COLOR_BayerBG2BGR)  # OpenCV's "BG" is the RGGB layout


def _photosites(camera: CameraModel, base: np.ndarray, layout: ScreenLayout, spots_yz: np.ndarray,
                seen: np.ndarray, rng: np.random.Generator, options: RenderOptions,
                beams: np.ndarray | None = None) -> np.ndarray:
    """Noise-free signal (H, W) float32 DN at each photosite: ambient light plus the lasers (beams (2, 3):
    their directions, None for round spots)."""
    sites = _bayer_sites(camera.height, camera.width)
    scene = base * _ambient_response(camera.height, camera.width)
    _, vignetting = _screen_maps(camera, layout)
    for laser in range(2):
        if not seen[laser]:
            continue
        spot = _spot(camera, layout, spots_yz[laser], options.laser_radiance_dn[laser], rng, options,
                     None if beams is None else beams[laser])
        if spot is None:
            continue
        row0, col0, patch = spot
        rows = slice(max(row0, 0), min(row0 + patch.shape[0], camera.height))
        cols = slice(max(col0, 0), min(col0 + patch.shape[1], camera.width))
        patch = patch[rows.start - row0:rows.stop - row0, cols.start - col0:cols.stop - col0]
        response = LASER_BGR[laser].astype(np.float32)[sites[rows, cols]]
        scene[rows, cols] += patch * response * vignetting[rows, cols]
    return scene


def render_frame(camera: CameraModel, spots_yz: np.ndarray, seen: np.ndarray, rng: np.random.Generator,
                 options: RenderOptions = RenderOptions(), layout: ScreenLayout = ScreenLayout(),
                 beams: np.ndarray | None = None) -> np.ndarray:
    """A bgr8 frame (H, W, 3) uint8 of the screen with the laser spots on it.

    spots_yz (2, 2): (y, z) in metres of laser 1 (row 0, red) and laser 2 (row
    1, green) on the plane x = 0; seen (2,) bool: whether each beam reaches
    that plane (False: the laser is off or points away; nothing is drawn). A
    seen spot outside the measuring area is still drawn where it lands (screen
    border, wall), as a camera would see it. beams (2, 3): the beams' directions
    in frame {0}, for their elongated footprints; None: round spots.
    """
    spots_yz = np.asarray(spots_yz, dtype=float).reshape(2, 2)
    seen = np.asarray(seen, dtype=bool).reshape(2)
    if not np.all(np.isfinite(spots_yz[seen])):
        raise ValueError(f"a seen spot must have finite coordinates, got {spots_yz.tolist()}")
    albedo, vignetting = _screen_maps(camera, layout)
    base = _ambient(camera, rng, options) * albedo * vignetting
    scene = _photosites(camera, base, layout, spots_yz, seen, rng, options, beams)
    return _expose(scene, rng, options)


def render_fiducial_frame(camera: CameraModel, rng: np.random.Generator, options: RenderOptions = RenderOptions(),
                          layout: ScreenLayout = ScreenLayout()) -> np.ndarray:
    """A bgr8 frame (H, W, 3) of the screen and its fiducials, lasers off (for calibrate_screen)."""
    return render_frame(camera, np.zeros((2, 2)), np.zeros(2, bool), rng, options, layout)


@lru_cache(maxsize=2)
def _board_texture(spec: CharucoSpec) -> tuple[np.ndarray, float, float]:
    """The ChArUco board with a white margin of half a square: (texture, texel m, margin m).

    texture (N, M, 2) float32: albedo, and 1 (coverage: resampled, it tells
    how much of a pixel the board covers).
    """
    texels_per_square = 80
    texel = spec.square / texels_per_square
    image = spec.board().generateImage((spec.squares_x * texels_per_square, spec.squares_y * texels_per_square),
                                       marginSize=0, borderBits=1)
    margin = texels_per_square // 2
    image = cv2.copyMakeBorder(image, margin, margin, margin, margin, cv2.BORDER_CONSTANT, value=255)
    albedo = INK_ALBEDO + (SCREEN_ALBEDO - INK_ALBEDO) * (image.astype(np.float32) / 255.0)
    return np.stack([albedo, np.ones_like(albedo)], axis=-1), texel, margin * texel


def render_board_frame(camera: CameraModel, rvec: np.ndarray, tvec: np.ndarray, rng: np.random.Generator,
                       spec: CharucoSpec = CharucoSpec(), options: RenderOptions = RenderOptions(),
                       layout: ScreenLayout = ScreenLayout()) -> np.ndarray:
    """A bgr8 frame (H, W, 3) of the ChArUco board held in front of the screen, lasers off.

    (rvec, tvec) (3,): pose of the board in the camera frame (board point
    (x, y, 0) in metres, origin at its first chessboard corner's outer square
    corner as in cv2.aruco.CharucoBoard, maps to R x + t).
    """
    rays = _normalised_rays(camera)
    xy = _rays_to_board(rays, rvec, tvec)
    texture, texel, margin = _board_texture(spec)
    col = (xy[..., 0] + margin) / texel - 0.5
    row = (xy[..., 1] + margin) / texel - 0.5
    board = _sample(texture, col, row, (0.0, 0.0))
    screen_albedo, vignetting = _screen_maps(camera, layout)
    albedo = board[..., 0] + (1.0 - board[..., 1]) * screen_albedo  # the screen shows where the board is not
    base = _ambient(camera, rng, options) * albedo * vignetting
    scene = base * _ambient_response(camera.height, camera.width)
    return _expose(scene, rng, options)


def board_poses(camera: CameraModel, spec: CharucoSpec = CharucoSpec(), count: int = 15,
                rng: np.random.Generator | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Poses (rvec, tvec) of the board in the camera frame for a calibration session.

    The board's centre visits a 5 x 3 grid over the image (so its corners
    sample the lens distortion out to the image corners) at 1.2 to 1.8 m,
    tilted 20 to 40 degrees about alternating axes; a pose is pulled towards
    the image centre until the whole board is in view.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    size = np.array([spec.squares_x * spec.square, spec.squares_y * spec.square])
    outline = np.array([[0, 0, 0], [size[0], 0, 0], [size[0], size[1], 0], [0, size[1], 0]], float)
    grid = [(gx, gy) for gy in (-0.3, 0.0, 0.3) for gx in (-0.36, -0.18, 0.0, 0.18, 0.36)]
    poses = []
    for k in range(count):
        gx, gy = grid[k % len(grid)]
        distance = rng.uniform(1.2, 1.8)
        tilt = np.radians(rng.uniform(20.0, 40.0)) * rng.choice([-1.0, 1.0])
        axis = np.array([1.0, 0.0, 0.0]) if k % 2 else np.array([0.0, 1.0, 0.0])
        rotation = cv2.Rodrigues(axis * tilt)[0] @ cv2.Rodrigues(np.array([0.0, 0.0, rng.uniform(-0.2, 0.2)]))[0]
        rvec = cv2.Rodrigues(rotation)[0].ravel()
        for shrink in np.linspace(1.0, 0.0, 11):
            target = np.array([gx * shrink * camera.width, gy * shrink * camera.height])
            centre_ray = np.linalg.solve(camera.K, np.array([camera.width / 2 + target[0],
                                                            camera.height / 2 + target[1], 1.0]))
            tvec = centre_ray * distance - rotation @ np.array([size[0] / 2, size[1] / 2, 0.0])
            pixels, _ = cv2.projectPoints(outline, rvec, tvec, camera.K, camera.dist)
            pixels = pixels.reshape(-1, 2)
            if np.all((pixels > 20) & (pixels < [camera.width - 20, camera.height - 20])):
                break
        poses.append((rvec, tvec))
    return poses
