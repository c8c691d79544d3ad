"""The scene frame recovers what synthetic rigs look at, and maps the dataset's units exactly."""

import numpy as np
import pytest

from signerf_jax import camera
from signerf_jax.data import frame as frame_lib
from signerf_jax.data import poses
from signerf_jax.errors import InputError

TARGET = np.array([1.5, -0.7, 0.4])


def rig_cameras(eyes, targets, width=64, height=48, focal=60.0):
  camera_to_world = np.asarray(camera.look_at(np.asarray(eyes, np.float32),
                                              np.asarray(targets, np.float32)))
  return camera.Cameras.create(camera_to_world, fx=focal, width=width, height=height)


def ring(count=24, radius=4.0, height=1.0, target=TARGET):
  angles = np.linspace(0, 2 * np.pi, count, endpoint=False)
  eyes = target + np.stack([radius * np.cos(angles), radius * np.sin(angles),
                            np.full(count, height)], -1)
  return eyes


def hemisphere(count=40, radius=3.0, target=TARGET, seed=0):
  rng = np.random.default_rng(seed)
  directions = rng.normal(size=(count, 3))
  directions[:, 2] = np.abs(directions[:, 2]) + 0.2
  directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
  return target + radius * directions


@pytest.mark.parametrize("eyes", [ring(), hemisphere(), ring(count=5, height=0.0)],
                         ids=["ring", "hemisphere", "five-camera ring"])
def test_centre_is_the_point_the_cameras_look_at(eyes):
  cameras = rig_cameras(eyes, np.broadcast_to(TARGET, eyes.shape))
  assert frame_lib.classify(cameras) == "unbounded"
  np.testing.assert_allclose(frame_lib.nearest_point_to_axes(cameras), TARGET, atol=1e-4)
  frame = frame_lib.estimate_frame(cameras)
  assert frame.kind == "unbounded"
  np.testing.assert_allclose(poses.transform_points(frame.world_from_source, TARGET), 0,
                             atol=1e-4)
  # Every camera lies inside the inner region, the farthest on its border.
  positions = poses.transform_points(frame.world_from_source, eyes)
  assert np.max(np.abs(positions)) == pytest.approx(1.0, abs=1e-5)
  assert frame.describe()["center_in_source_units"] == pytest.approx(TARGET.tolist(), abs=1e-4)


def test_sfm_points_refine_an_off_centre_subject():
  """Hand-held cameras aim roughly (up to ~8 degrees off) at an object away from the ring's
  centre; the room's points surround everything. The central SfM points find the object."""
  rng = np.random.default_rng(1)
  eyes = ring(count=30, radius=3.0, height=1.2, target=np.zeros(3))
  subject = np.array([0.6, 0.3, 0.2])
  aims = subject + rng.normal(scale=0.4, size=eyes.shape)
  cameras = rig_cameras(eyes, aims)
  object_points = subject + rng.normal(scale=0.1, size=(400, 3))
  angles = rng.uniform(0, 2 * np.pi, 2000)
  room_points = np.stack([6 * np.cos(angles), 6 * np.sin(angles),
                          rng.uniform(-1, 3, 2000)], -1)
  points = np.concatenate([object_points, room_points])
  axes_only = frame_lib.estimate_frame(cameras)
  with_points = frame_lib.estimate_frame(cameras, points=points)
  error = lambda frame: np.linalg.norm(frame.describe()["center_in_source_units"] - subject)
  assert error(with_points) < 0.05 < error(axes_only)
  assert "SfM points" in with_points.method
  # The near plane stays in front of the nearest content (the object, ~2.6 units away).
  nearest = np.min(np.linalg.norm(eyes[:, None] - points[None], axis=-1))
  assert 0 < with_points.near < nearest * with_points.scale


def test_forward_facing_rig_is_framed_by_its_content_depths():
  eyes = np.stack([np.linspace(-1, 1, 9), np.zeros(9), np.zeros(9)], -1)
  cameras = rig_cameras(eyes, eyes + [0.0, 0.0, -1.0])
  assert frame_lib.classify(cameras) == "forward_facing"
  rng = np.random.default_rng(2)
  wall = np.stack([rng.uniform(-3, 3, 500), rng.uniform(-2, 2, 500),
                   rng.uniform(-10.5, -9.5, 500)], -1)
  frame = frame_lib.estimate_frame(cameras, points=wall)
  assert frame.kind == "forward_facing" and "SfM point depths" in frame.method
  inside = poses.transform_points(frame.world_from_source, wall)
  visible = np.all(np.abs(wall[:, :2]) < 2, axis=-1)
  assert np.all(np.abs(inside[visible]) <= 1.0 + 1e-6)
  # Rays cover the wall's depths (9.5 .. 10.5 source units) and start well before them.
  assert frame.near <= 9.6 * frame.scale and frame.far >= 10.4 * frame.scale
  assert frame.near > 5.0 * frame.scale


def test_overrides_give_the_exact_frame():
  cameras = rig_cameras(ring(), np.broadcast_to(TARGET, (24, 3)))
  centre, radius = np.array([1.0, 2.0, 3.0]), 2.5
  frame = frame_lib.estimate_frame(cameras, scene_center=centre, scene_radius=radius)
  np.testing.assert_allclose(poses.transform_points(frame.world_from_source, centre), 0,
                             atol=1e-9)
  assert frame.scale == pytest.approx(1 / radius)
  with pytest.raises(InputError) as error:
    frame_lib.estimate_frame(cameras, scene_radius=0.0)
  assert error.value.field == "scene_radius"
  with pytest.raises(InputError):
    frame_lib.estimate_frame(cameras, kind="bounded")
