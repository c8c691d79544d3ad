import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from signerf_jax import camera, lens

# OpenCV's perspective model, (k1, k2, p1, p2, k3, k4, k5, k6): a pinhole, two radial-tangential
# lenses and a rational one (a wide-angle calibration's shape: the denominator tames the corners).
DISTORTIONS = [(0.0,) * 8, (-0.3, 0.1, 0.001, -0.002, 0.0, 0.0, 0.0, 0.0),
               (0.2, 0.05, -0.01, 0.005, 0.0, 0.0, 0.0, 0.0),
               (0.4, -0.1, 0.002, -0.001, 0.02, 0.7, -0.05, 0.01)]
# cv2.fisheye's (k1, k2, k3, k4): the ideal equidistant lens and two calibrated shapes.
FISHEYE_DISTORTIONS = [(0.0,) * 4, (0.05, -0.01, 0.002, -0.0005), (-0.03, 0.004, 0.0, 0.0)]
LENSES = ([(distortion, False) for distortion in DISTORTIONS]
          + [(distortion, True) for distortion in FISHEYE_DISTORTIONS])
LENS_IDS = [f"{'fisheye' if fisheye else 'perspective'}{index}"
            for index, (_, fisheye) in enumerate(LENSES)]


def make_cameras(distortion=None, fisheye=False, focal_scale=1.0):
  """Three 64 x 48 cameras looking at the origin; a fisheye sees 130-165 degrees (diagonal)."""
  eyes = np.array([[3.0, 0.0, 1.0], [0.0, -2.0, 0.5], [0.1, 0.2, 4.0]], np.float32)
  camera_to_world = camera.look_at(eyes, np.zeros(3, np.float32))
  scale = focal_scale * (0.7 if fisheye else 1.0)
  return camera.Cameras.create(camera_to_world, fx=np.array([50.0, 60.0, 40.0]) * scale,
                               fy=np.array([52.0, 60.0, 41.0]) * scale, cx=31.0, cy=25.5,
                               width=64, height=48, distortion=distortion, fisheye=fisheye)


def image_grid_pixels(cameras, count=15):
  """[count^2, 2] pixel positions spread over the whole image, its four corners included."""
  columns, rows = np.meshgrid(np.linspace(0, cameras.width, count),
                              np.linspace(0, cameras.height, count))
  return np.stack([columns.ravel(), rows.ravel()], -1).astype(np.float32)


def opencv_pose(cameras, index):
  """cv2's (rvec, tvec) world-to-camera pose of one OpenGL camera-to-world."""
  camera_to_world = np.asarray(cameras.camera_to_world[index], np.float64)
  rotation = np.diag([1.0, -1.0, -1.0]) @ camera_to_world[:, :3].T
  return cv2.Rodrigues(rotation)[0], -rotation @ camera_to_world[:, 3]


@pytest.mark.parametrize("up", [(0, 0, 1), (0, 0, -1), (1, 0, 0)])
@pytest.mark.parametrize("eye", [(3, 0, 1), (0, 0, 5), (0, 0, -5), (1e-3, 0, 2)])
def test_look_at_is_a_rotation_looking_at_the_target(eye, up):
  target = np.array([0.5, -0.25, 0.0], np.float32)
  camera_to_world = np.asarray(camera.look_at(np.asarray(eye, np.float32), target, up))
  rotation = camera_to_world[:, :3]
  np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-5)
  assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-5)
  to_target = target - np.asarray(eye, np.float32)
  np.testing.assert_allclose(-rotation[:, 2], to_target / np.linalg.norm(to_target), atol=1e-5)


@pytest.mark.parametrize("distortion, expected", [
    (None, [0.0] * 8), ((0.1, 0.2, 0.3, 0.4), [0.1, 0.2, 0.3, 0.4, 0, 0, 0, 0]),
    ((0.1, 0.2, 0.3, 0.4, 0.5), [0.1, 0.2, 0.3, 0.4, 0.5, 0, 0, 0]),
    ((1, 2, 3, 4, 5, 6, 7, 8), [1, 2, 3, 4, 5, 6, 7, 8])])
def test_create_pads_opencv_coefficients_to_eight(distortion, expected):
  cameras = make_cameras(distortion)
  assert cameras.distortion.shape == (3, 8)
  np.testing.assert_allclose(cameras.distortion, np.broadcast_to(expected, (3, 8)), rtol=1e-6)
  per_camera = np.arange(12, dtype=np.float32).reshape(3, 4)
  np.testing.assert_array_equal(make_cameras(per_camera).distortion[:, :4], per_camera)


def test_create_rejects_other_coefficient_counts_and_a_fisheye_with_more_than_four():
  with pytest.raises(ValueError, match="OpenCV coefficients"):
    make_cameras((0.1, 0.2, 0.3))
  with pytest.raises(ValueError, match="four coefficients"):
    make_cameras((0.1, 0.2, 0.3, 0.4, 0.5), fisheye=True)


def test_every_derived_batch_keeps_the_lens_model():
  cameras = make_cameras(FISHEYE_DISTORTIONS[1], fisheye=True)
  boxes = np.array([[0.0, 0.0, 32.0, 24.0]] * 3, np.float32)
  derived = [cameras.take([2, 0]), cameras.take(slice(1, 3)), cameras.resized(32, 24),
             cameras.downscaled(2), cameras.cropped(boxes, 16, 12),
             jax.tree.map(lambda array: array, cameras)]
  assert all(batch.fisheye for batch in derived)
  assert not make_cameras().take([0]).fisheye


@pytest.mark.parametrize("distortion", DISTORTIONS)
def test_distort_matches_opencv(distortion):
  rng = np.random.default_rng(0)
  points = rng.uniform(-0.6, 0.6, (100, 2)).astype(np.float32)
  x, y = lens.distort(points[:, 0], points[:, 1], jnp.asarray(distortion, jnp.float32))
  homogeneous = np.concatenate([points, np.ones((100, 1), np.float32)], -1)
  expected, _ = cv2.projectPoints(homogeneous, np.zeros(3), np.zeros(3), np.eye(3),
                                  np.asarray(distortion, np.float64))
  np.testing.assert_allclose(np.stack([x, y], -1), expected[:, 0], atol=1e-5)


@pytest.mark.parametrize("distortion", FISHEYE_DISTORTIONS)
def test_fisheye_distort_matches_opencv(distortion):
  rng = np.random.default_rng(0)
  points = rng.uniform(-2.0, 2.0, (100, 2)).astype(np.float32)  # up to 70 degrees off the axis
  coefficients = jnp.asarray(distortion + (0.0,) * 4, jnp.float32)
  x, y = lens.distort(points[:, 0], points[:, 1], coefficients, fisheye=True)
  expected = cv2.fisheye.distortPoints(points[:, None].astype(np.float64), np.eye(3),
                                       np.asarray(distortion, np.float64))
  np.testing.assert_allclose(np.stack([x, y], -1), expected[:, 0], atol=1e-5)


@pytest.mark.parametrize("distortion, fisheye", LENSES, ids=LENS_IDS)
def test_undistort_round_trips_over_the_whole_image_and_matches_opencv(distortion, fisheye):
  """Distorted coordinates of pixels all over the image, corners included, come back through
  undistort -> distort to 1e-3 px; OpenCV's own undistortion agrees to 1e-4 (normalised)."""
  cameras = make_cameras(distortion, fisheye)
  pixels = image_grid_pixels(cameras)
  fx, fy, cx, cy = (float(value[0]) for value in (cameras.fx, cameras.fy, cameras.cx, cameras.cy))
  x_distorted, y_distorted = (pixels[:, 0] - cx) / fx, (pixels[:, 1] - cy) / fy
  coefficients = cameras.distortion[0]
  x, y = lens.undistort(x_distorted, y_distorted, coefficients, fisheye)
  assert np.all(np.isfinite(x)) and np.all(np.isfinite(y))
  again = np.stack(lens.distort(x, y, coefficients, fisheye), -1)
  np.testing.assert_allclose(again * [fx, fy] + [cx, cy], pixels, atol=1e-3)

  distorted = np.stack([x_distorted, y_distorted], -1)[:, None].astype(np.float64)
  criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
  if fisheye:
    opencv = cv2.fisheye.undistortPoints(distorted, np.eye(3), np.asarray(distortion),
                                         criteria=criteria)
  else:
    opencv = cv2.undistortPoints(distorted, np.eye(3), np.asarray(distortion), criteria=criteria)
  np.testing.assert_allclose(np.stack([x, y], -1), opencv[:, 0], atol=1e-4, rtol=1e-5)


@pytest.mark.parametrize("distortion, fisheye", [((-0.5, 0.0, 0.0, 0.0), False),
                                                 ((-0.2, 0.0, 0.0, 0.0), True)])
def test_undistort_stays_finite_where_the_lens_folds_over(distortion, fisheye):
  """Strong barrel lenses whose model folds back (r - 0.5 r^3 peaks at r = 0.82; the fisheye's
  theta_d peaks at 74 degrees), probed out to 20 times past the fold."""
  coefficients = make_cameras(distortion, fisheye).distortion[0]
  points = np.linspace(-20.0, 20.0, 41, dtype=np.float32)
  x, y = lens.undistort(points, points[::-1], coefficients, fisheye)
  directions = lens.camera_directions(points, points[::-1], coefficients, fisheye)
  assert np.all(np.isfinite(x)) and np.all(np.isfinite(y))
  np.testing.assert_allclose(np.linalg.norm(directions, axis=-1), 1.0, atol=1e-6)


@pytest.mark.parametrize("distortion, fisheye", LENSES, ids=LENS_IDS)
def test_project_matches_opencv(distortion, fisheye):
  """Pixels of world points within 70 degrees of each axis agree with cv2.projectPoints /
  cv2.fisheye.projectPoints to 2e-3 px (float32 against float64)."""
  cameras = make_cameras(distortion, fisheye)
  points = np.random.default_rng(4).uniform(-0.8, 0.8, (60, 3)).astype(np.float32)
  pixels, z_depth = camera.project(cameras, points)
  assert np.all(np.asarray(z_depth) > 0)
  for index in range(cameras.num_cameras):
    rotation_vector, translation = opencv_pose(cameras, index)
    intrinsics = np.asarray(cameras.intrinsic_matrices()[index], np.float64)
    world = points[:, None].astype(np.float64)
    if fisheye:
      expected, _ = cv2.fisheye.projectPoints(world, rotation_vector, translation, intrinsics,
                                              np.asarray(distortion, np.float64))
    else:
      expected, _ = cv2.projectPoints(world, rotation_vector, translation, intrinsics,
                                      np.asarray(distortion, np.float64))
    np.testing.assert_allclose(pixels[index], expected[:, 0], atol=2e-3)


@pytest.mark.parametrize("distortion, fisheye", LENSES, ids=LENS_IDS)
def test_rays_project_back_to_their_pixels(distortion, fisheye):
  cameras = make_cameras(distortion, fisheye)
  rng = np.random.default_rng(2)
  count = 50
  indices = np.concatenate([rng.integers(0, cameras.num_cameras, count), [0, 1, 2, 0]])
  corners = image_grid_pixels(cameras, 2)  # the four image corners
  pixel_x = np.concatenate([rng.uniform(0, cameras.width, count), corners[:, 0]])
  pixel_y = np.concatenate([rng.uniform(0, cameras.height, count), corners[:, 1]])
  pixel_x, pixel_y = pixel_x.astype(np.float32), pixel_y.astype(np.float32)
  rays = camera.pixel_rays(cameras, indices, pixel_x, pixel_y)
  np.testing.assert_allclose(np.linalg.norm(rays.directions, axis=-1), 1.0, atol=1e-6)
  distance = rng.uniform(0.5, 5.0, len(indices)).astype(np.float32)
  points = rays.origins + distance[:, None] * rays.directions
  pixels, z_depth = camera.project(cameras, points)
  own = (indices, np.arange(len(indices)))
  np.testing.assert_allclose(np.asarray(pixels)[own], np.stack([pixel_x, pixel_y], -1), atol=2e-3)
  np.testing.assert_allclose(np.asarray(z_depth)[own], distance * rays.cos_to_optical_axis,
                             rtol=1e-5, atol=1e-6)


def test_fisheye_wider_than_180_degrees_gives_unit_rays_that_project_back():
  """An equidistant-like fisheye whose image corners are 125 degrees off the axis (a 250
  degree diagonal field): every pixel's ray is unit and finite, the outer ones point behind the
  camera plane, and projecting them returns their pixels."""
  eye = np.array([[0.0, 0.0, 0.0]], np.float32)
  camera_to_world = camera.look_at(eye, np.array([0.0, 1.0, 0.0], np.float32))
  corner_theta = np.deg2rad(125.0)
  focal = np.hypot(32.0, 24.0) / corner_theta
  cameras = camera.Cameras.create(camera_to_world, fx=focal, width=64, height=48,
                                  distortion=(0.01, -0.002, 0.0, 0.0), fisheye=True)
  rays = camera.image_rays(cameras, 0)
  directions = np.asarray(rays.directions)
  assert np.all(np.isfinite(directions)) and np.all(np.isfinite(rays.cos_to_optical_axis))
  np.testing.assert_allclose(np.linalg.norm(directions, axis=-1), 1.0, atol=1e-6)
  assert np.min(rays.cos_to_optical_axis) < np.cos(np.deg2rad(115.0))
  # cos_to_optical_axis is the component along the viewing direction (the z-depth factor).
  np.testing.assert_allclose(directions @ np.asarray(cameras.forward[0]),
                             rays.cos_to_optical_axis, atol=1e-6)
  pixels, _ = camera.project(cameras, rays.origins + 2.0 * rays.directions)
  rows, columns = np.meshgrid(np.arange(48) + 0.5, np.arange(64) + 0.5, indexing="ij")
  np.testing.assert_allclose(pixels[0], np.stack([columns, rows], -1), atol=2e-3)


def test_image_rays_centre_looks_forward_and_pixel_grid_is_row_major():
  cameras = make_cameras()
  rays = camera.image_rays(cameras, 1)
  assert rays.shape == (48, 64)
  pixels, _ = camera.project(cameras, rays.origins + rays.directions)
  np.testing.assert_allclose(pixels[1, 10, 20], [20.5, 10.5], atol=1e-3)
  centre = camera.pixel_rays(cameras, 1, cameras.cx[1], cameras.cy[1])
  np.testing.assert_allclose(centre.directions, cameras.forward[1], atol=1e-6)
  assert float(centre.cos_to_optical_axis) == pytest.approx(1.0)


@pytest.mark.slow
@pytest.mark.parametrize("per_side", [1, 2, 3])
def test_subpixel_rays_cross_a_grid_inside_each_pixel_pixel_by_pixel(per_side):
  """Pixel i's per_side^2 rays come at i * per_side^2 onwards, row by row through the centres
  of a per_side x per_side grid of sub-pixels (whose mean is the pixel's centre); image_rays at
  one of those positions crosses every pixel there."""
  cameras = make_cameras()
  positions = camera.subpixel_positions(per_side)
  assert positions.shape == (per_side**2, 2)
  np.testing.assert_allclose(positions.mean(axis=0), [0.5, 0.5], atol=1e-6)
  assert np.all((positions > 0) & (positions < 1))
  indices, rows, columns = np.array([2, 0, 1]), np.array([0, 47, 13]), np.array([63, 0, 30])
  rays = camera.subpixel_rays(cameras, indices, rows, columns, per_side)
  assert rays.shape == (3 * per_side**2,)
  for pixel in range(3):
    for position_index, (x, y) in enumerate(positions):
      ray = jax.tree.map(lambda array: array[pixel * per_side**2 + position_index], rays)
      projected, _ = camera.project(cameras.take([indices[pixel]]),
                                    ray.origins + 2.0 * ray.directions)
      np.testing.assert_allclose(projected[0], [columns[pixel] + x, rows[pixel] + y], atol=2e-3)
      assert int(ray.camera_indices) == indices[pixel]
  x, y = positions[-1]
  whole = camera.image_rays(cameras, 2, (float(x), float(y)))
  pixels, _ = camera.project(cameras.take([2]), whole.origins + whole.directions)
  np.testing.assert_allclose(pixels[0, 0, 63], [63 + x, y], atol=2e-3)


def test_points_behind_the_camera_have_negative_depth():
  cameras = make_cameras()
  behind = cameras.positions[0] - 2.0 * cameras.forward[0]
  _, z_depth = camera.project(cameras.take([0]), behind)
  assert float(z_depth[0]) == pytest.approx(-2.0, abs=1e-5)


def test_resized_scales_intrinsics():
  cameras = make_cameras().downscaled(2)
  assert (cameras.width, cameras.height) == (32, 24)
  np.testing.assert_allclose(cameras.fx, [25.0, 30.0, 20.0])
  np.testing.assert_allclose(cameras.cy, 12.75)


@pytest.mark.parametrize("distortion, fisheye", LENSES, ids=LENS_IDS)
def test_cropped_cameras_see_what_the_crop_of_the_image_shows(distortion, fisheye):
  cameras = make_cameras(distortion, fisheye)
  # Boxes inside, across the edge of and larger than the 64 x 48 frame; tiles of 40 x 30.
  boxes = np.array([[10.0, 5.0, 24.0, 18.0], [-6.0, 30.0, 20.0, 15.0], [-8.0, -6.0, 80.0, 60.0]],
                   np.float32)
  cropped = cameras.cropped(boxes, 40, 30)
  assert (cropped.width, cropped.height) == (40, 30)
  rng = np.random.default_rng(3)
  columns, rows = rng.integers(0, 40, 20), rng.integers(0, 30, 20)
  for index in range(cameras.num_cameras):
    x0, y0, box_width, box_height = boxes[index]
    tile = camera.pixel_rays(cropped, index, columns + 0.5, rows + 0.5)
    source = camera.pixel_rays(cameras, index, x0 + (columns + 0.5) * box_width / 40,
                               y0 + (rows + 0.5) * box_height / 30)
    np.testing.assert_allclose(tile.directions, source.directions, atol=1e-5)
    np.testing.assert_allclose(tile.origins, source.origins, atol=1e-6)


@pytest.mark.parametrize("fisheye", [False, True], ids=["perspective", "fisheye"])
def test_random_rays_stay_in_range_and_do_not_recompile(fisheye):
  cameras = make_cameras(FISHEYE_DISTORTIONS[1] if fisheye else DISTORTIONS[3], fisheye)
  sample = jax.jit(camera.random_rays, static_argnums=2)
  rays, (index, row, column) = sample(jax.random.PRNGKey(0), cameras, 256)
  assert rays.shape == (256,)
  assert index.max() < 3 and row.max() < 48 and column.max() < 64 and min(
      index.min(), row.min(), column.min()) >= 0
  assert np.all(np.isfinite(rays.directions))
  sizes_before = sample._cache_size()
  sample(jax.random.PRNGKey(1), cameras, 256)
  other_coefficients = cameras.replace(distortion=cameras.distortion * 0.5)
  sample(jax.random.PRNGKey(2), other_coefficients, 256)
  assert sample._cache_size() == sizes_before
