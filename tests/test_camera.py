import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from signerf_jax import camera

DISTORTIONS = [(0.0, 0.0, 0.0, 0.0), (-0.3, 0.1, 0.001, -0.002), (0.2, 0.05, -0.01, 0.005)]


def make_cameras(distortion=(0.0, 0.0, 0.0, 0.0)):
  eyes = np.array([[3.0, 0.0, 1.0], [0.0, -2.0, 0.5], [0.1, 0.2, 4.0]], np.float32)
  camera_to_world = camera.look_at(eyes, np.zeros(3, np.float32))
  return camera.Cameras.create(camera_to_world, fx=[50.0, 60.0, 40.0], fy=[52.0, 60.0, 41.0],
                               cx=31.0, cy=25.5, width=64, height=48, distortion=distortion)


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


@pytest.mark.parametrize("distortion", DISTORTIONS)
def test_distort_matches_opencv(distortion):
  rng = np.random.default_rng(0)
  points = rng.uniform(-0.6, 0.6, (100, 2)).astype(np.float32)
  x, y = camera.distort(points[:, 0], points[:, 1], jnp.asarray(distortion, jnp.float32))
  homogeneous = np.concatenate([points, np.ones((100, 1), np.float32)], -1)
  expected, _ = cv2.projectPoints(homogeneous, np.zeros(3), np.zeros(3), np.eye(3),
                                  np.asarray(distortion, np.float64))
  np.testing.assert_allclose(np.stack([x, y], -1), expected[:, 0], atol=1e-5)


@pytest.mark.parametrize("distortion", DISTORTIONS)
def test_undistort_inverts_distort_like_opencv(distortion):
  rng = np.random.default_rng(1)
  points = rng.uniform(-0.5, 0.5, (200, 2)).astype(np.float32)
  coefficients = jnp.asarray(distortion, jnp.float32)
  distorted = camera.distort(points[:, 0], points[:, 1], coefficients)
  recovered = np.stack(camera.undistort(*distorted, coefficients), -1)
  np.testing.assert_allclose(recovered, points, atol=2e-5)
  opencv = cv2.undistortPoints(np.stack(distorted, -1)[:, None].astype(np.float64), np.eye(3),
                               np.asarray(distortion, np.float64),
                               criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12))
  np.testing.assert_allclose(recovered, opencv[:, 0], atol=2e-5)


@pytest.mark.parametrize("distortion", DISTORTIONS)
def test_rays_project_back_to_their_pixels(distortion):
  cameras = make_cameras(distortion)
  rng = np.random.default_rng(2)
  count = 50
  indices = rng.integers(0, cameras.num_cameras, count)
  pixel_x = rng.uniform(0, cameras.width, count).astype(np.float32)
  pixel_y = rng.uniform(0, cameras.height, count).astype(np.float32)
  rays = camera.pixel_rays(cameras, indices, pixel_x, pixel_y)
  np.testing.assert_allclose(np.linalg.norm(rays.directions, axis=-1), 1.0, atol=1e-6)
  distance = rng.uniform(0.5, 5.0, count).astype(np.float32)
  points = rays.origins + distance[:, None] * rays.directions
  pixels, z_depth = camera.project(cameras, points)
  own = (indices, np.arange(count))
  np.testing.assert_allclose(np.asarray(pixels)[own], np.stack([pixel_x, pixel_y], -1), atol=2e-3)
  np.testing.assert_allclose(np.asarray(z_depth)[own], distance * rays.cos_to_optical_axis,
                             rtol=1e-5)


def test_image_rays_centre_looks_forward_and_pixel_grid_is_row_major():
  cameras = make_cameras()
  rays = camera.image_rays(cameras, 1)
  assert rays.shape == (48, 64)
  pixels, _ = camera.project(cameras, rays.origins + rays.directions)
  np.testing.assert_allclose(pixels[1, 10, 20], [20.5, 10.5], atol=1e-3)
  centre = camera.pixel_rays(cameras, 1, cameras.cx[1], cameras.cy[1])
  np.testing.assert_allclose(centre.directions, cameras.forward[1], atol=1e-6)
  assert float(centre.cos_to_optical_axis) == pytest.approx(1.0)


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


@pytest.mark.parametrize("distortion", DISTORTIONS)
def test_cropped_cameras_see_what_the_crop_of_the_image_shows(distortion):
  cameras = make_cameras(distortion)
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


def test_random_rays_stay_in_range_and_do_not_recompile():
  cameras = make_cameras((-0.3, 0.1, 0.001, -0.002))
  sample = jax.jit(camera.random_rays, static_argnums=2)
  rays, (index, row, column) = sample(jax.random.PRNGKey(0), cameras, 256)
  assert rays.shape == (256,)
  assert index.max() < 3 and row.max() < 48 and column.max() < 64 and min(
      index.min(), row.min(), column.min()) >= 0
  sizes_before = sample._cache_size()
  sample(jax.random.PRNGKey(1), cameras, 256)
  assert sample._cache_size() == sizes_before
