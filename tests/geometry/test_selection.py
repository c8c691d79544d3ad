import numpy as np
import pytest

from signerf_jax import camera
from signerf_jax.errors import InputError
from signerf_jax.geometry import selection

SIZE = 40
HEIGHT = 4.0
FOCAL = 30.0


def downward_cameras(offsets=((0.0, 0.0),)):
  """Cameras at height HEIGHT above the ground plane z = 0, looking straight down."""
  eyes = np.array([[x, y, HEIGHT] for x, y in offsets], np.float32)
  targets = eyes * np.array([1, 1, 0], np.float32)
  camera_to_world = camera.look_at(eyes, targets, up=(0.0, 1.0, 0.0))
  return camera.Cameras.create(camera_to_world, fx=FOCAL, width=SIZE, height=SIZE)


def ground_z_depth(cameras):
  """The ground plane's z-depth: HEIGHT everywhere for a camera looking straight down."""
  return np.full((cameras.num_cameras, SIZE, SIZE), HEIGHT, np.float32)


def ground_points(cameras):
  """[N, H, W, 3] ground point seen through each pixel centre (independent of the code)."""
  columns, rows = np.meshgrid(np.arange(SIZE) + 0.5, np.arange(SIZE) + 0.5)
  x = (columns - SIZE / 2) / FOCAL * HEIGHT
  y = -(rows - SIZE / 2) / FOCAL * HEIGHT  # image rows grow downwards, world y upwards
  positions = np.asarray(cameras.positions)
  return np.stack([positions[:, None, None, 0] + x, positions[:, None, None, 1] + y,
                   np.zeros((len(positions), SIZE, SIZE))], -1)


def test_box_on_the_ground_gives_the_analytic_mask():
  cameras = downward_cameras([(0.0, 0.0), (0.7, -0.4)])  # the second sees it off-centre
  box = selection.Box.create([-0.51, -0.31, -0.1], [0.81, 0.61, 0.5])
  result = selection.shape_selection(cameras, box, ground_z_depth(cameras))
  points = ground_points(cameras)
  expected = np.all((points >= np.asarray(box.minimum)) & (points <= np.asarray(box.maximum)), -1)
  np.testing.assert_array_equal(result.mask, expected)
  # About (1.32 x 0.92) scene units at 7.5 pixels per unit.
  assert abs(expected[0].sum() - 1.32 * 0.92 * (FOCAL / HEIGHT)**2) < 20
  # The surface is inside the box wherever it is masked: control depth = NeRF depth.
  np.testing.assert_allclose(np.asarray(result.control_depth)[expected], HEIGHT, rtol=1e-6)


def test_floating_box_clamps_the_depth_to_its_back_face():
  cameras = downward_cameras()
  half = 0.47  # keeps the faces' edges off pixel centres
  box = selection.Box.create([-half, -half, 1.0], [half, half, 2.0])
  depth = ground_z_depth(cameras)
  surface = selection.shape_selection(cameras, box, depth)
  silhouette = selection.shape_selection(cameras, box, depth, mask_mode="silhouette")
  assert not np.asarray(surface.mask).any()  # the ground is below the box
  points = ground_points(cameras)
  # A ray through the box: the box's bottom face (z = 1) projects like a ground square scaled by
  # HEIGHT / (HEIGHT - 1); the top face (z = 2) is larger, so the silhouette is the top face.
  top_face = np.all(np.abs(points[..., :2] * (HEIGHT - 2.0) / HEIGHT) <= half, -1)
  bottom_face = np.all(np.abs(points[..., :2] * (HEIGHT - 1.0) / HEIGHT) <= half, -1)
  np.testing.assert_array_equal(silhouette.mask, top_face)
  control = np.asarray(silhouette.control_depth)
  np.testing.assert_allclose(control[bottom_face], HEIGHT - 1.0, rtol=1e-5)
  np.testing.assert_allclose(control[~top_face], HEIGHT, rtol=1e-6)  # rays missing the box
  # Through a side wall the exit lies between the two faces.
  walls = top_face & ~bottom_face
  assert walls.any()
  assert np.all((control[walls] > HEIGHT - 2.0) & (control[walls] < HEIGHT - 1.0 + 1e-5))
  np.testing.assert_array_equal(silhouette.control_depth, surface.control_depth)


def test_occluders_keep_their_depth_and_empty_pixels_count_as_far():
  cameras = downward_cameras()
  box = selection.Box.create([-1.0, -1.0, -0.5], [1.0, 1.0, 0.5])
  depth = ground_z_depth(cameras)
  depth[0, 18:22, 18:22] = 1.0  # an occluder high above the box
  accumulation = np.ones_like(depth)
  accumulation[0, 13:16, 18:22] = 0.2  # no NeRF content (transparent)
  result = selection.shape_selection(cameras, box, depth, accumulation)
  mask, control = np.asarray(result.mask), np.asarray(result.control_depth)
  assert not mask[0, 18:22, 18:22].any()
  np.testing.assert_allclose(control[0, 18:22, 18:22], 1.0)
  assert not mask[0, 13:16, 18:22].any()
  # Behind the box there is nothing: the control shows the box's back face (z = -0.5).
  np.testing.assert_allclose(control[0, 13:16, 18:22], HEIGHT + 0.5, rtol=1e-5)
  silhouette = selection.shape_selection(cameras, box, depth, accumulation,
                                         mask_mode="silhouette")
  assert np.asarray(silhouette.mask)[0, 13:16, 18:22].all()


def test_camera_inside_the_box():
  cameras = downward_cameras()
  box = selection.Box.create([-10.0, -10.0, -1.0], [10.0, 10.0, 5.0])  # holds the camera
  depth = ground_z_depth(cameras)
  depth[0, :, :10] = 50.0  # a surface far below, outside the box
  result = selection.shape_selection(cameras, box, depth)
  mask = np.asarray(result.mask)
  assert mask[0, :, 10:].all() and not mask[0, :, :10].any()
  control = np.asarray(result.control_depth)
  # The box's bottom face (z = -1) lies at z-depth HEIGHT + 1 below the camera.
  np.testing.assert_allclose(control[0, :, :10], HEIGHT + 1.0, rtol=1e-5)


def test_distance_and_z_depth_inputs_agree():
  cameras = downward_cameras([(0.3, 0.1)])
  box = selection.Box.create([-0.5, -0.5, -0.5], [0.5, 0.5, 0.5])
  z_depth = ground_z_depth(cameras)
  cosine = np.asarray(camera.image_rays(cameras, 0).cos_to_optical_axis)
  from_z = selection.shape_selection(cameras, box, z_depth)
  from_distance = selection.shape_selection(cameras, box, z_depth / cosine, depth_kind="distance")
  np.testing.assert_array_equal(from_z.mask, from_distance.mask)
  np.testing.assert_allclose(from_z.control_depth, from_distance.control_depth, rtol=1e-6)


def test_proxy_selection_composites_nearest_wins():
  cameras = downward_cameras()
  nerf = ground_z_depth(cameras)
  nerf[0, :, :5] = 1.0  # something tall next to the proxy
  accumulation = np.ones_like(nerf)
  accumulation[0, :, 35:] = 0.0  # no NeRF content on the right
  proxy = np.full_like(nerf, np.inf)
  proxy[0, 10:30, 0:40] = 3.0  # a proxy standing 1 unit tall
  result = selection.proxy_selection(cameras, nerf, proxy, accumulation)
  mask, control = np.asarray(result.mask)[0], np.asarray(result.control_depth)[0]
  assert mask[10:30, 5:].all()
  assert not mask[10:30, :5].any()  # hidden behind the tall thing
  assert not mask[:10].any() and not mask[30:].any()
  np.testing.assert_allclose(control[10:30, 5:], 3.0)
  np.testing.assert_allclose(control[:, :5], 1.0)
  np.testing.assert_allclose(control[:10, 5:35], HEIGHT)
  assert np.isinf(control[:10, 35:]).all()  # neither NeRF content nor proxy


def test_box_validation():
  with pytest.raises(InputError, match="must exceed"):
    selection.Box.create([0, 0, 0], [1, 0, 1])
  with pytest.raises(InputError, match="finite"):
    selection.Box.create([0, 0, np.nan], [1, 1, 1])
  with pytest.raises(InputError, match="mask_mode"):
    selection.shape_selection(downward_cameras(), selection.Box.create(-np.ones(3), np.ones(3)),
                              ground_z_depth(downward_cameras()), mask_mode="inside")
