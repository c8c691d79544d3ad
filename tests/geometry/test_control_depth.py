import numpy as np

from signerf_jax import camera
from signerf_jax.geometry import control_depth


def test_near_is_one_far_is_zero_and_nothing_is_zero():
  z_depth = np.array([[[1.0, 2.0, 4.0, 0.5, 8.0, np.inf, np.nan, 0.0, -1.0]]], np.float32)
  normalised = np.asarray(control_depth.normalize_control_depth(z_depth, 1.0, 4.0))[0, 0]
  np.testing.assert_allclose(normalised[:5], [1.0, 1.0 / 3.0, 0.0, 1.0, 0.0], atol=1e-6)
  np.testing.assert_array_equal(normalised[5:], 0.0)
  assert np.all(np.diff(np.asarray(control_depth.normalize_control_depth(
      np.linspace(1, 4, 50, dtype=np.float32)[None, None], 1.0, 4.0))[0, 0]) < 0)


def test_same_selection_fills_the_same_band_at_any_camera_distance():
  # The same sphere seen from two distances: its nearest and farthest points get the same values.
  center, radius = np.array([0.5, -0.2, 0.1], np.float32), 0.3
  eyes = center + np.array([[0, -2.0, 0], [0, -6.0, 0]], np.float32)
  cameras = camera.Cameras.create(camera.look_at(eyes, center), fx=10.0, width=4, height=4)
  near, far = control_depth.selection_depth_range(cameras, center, radius, padding=0.25)
  distance = np.array([2.0, 6.0])
  np.testing.assert_allclose(near, distance - 1.25 * radius, rtol=1e-6)
  np.testing.assert_allclose(far, distance + 1.25 * radius, rtol=1e-6)
  surface = np.stack([distance - radius, distance + radius], -1).astype(np.float32)[:, None]
  values = np.asarray(control_depth.normalize_control_depth(surface, near, far))[:, 0]
  assert np.all((values > 0.05) & (values < 0.95))
  # Nearly the same band (inverse depth bends it slightly more for the near camera).
  np.testing.assert_allclose(values[0], values[1], atol=0.05)


def test_camera_inside_the_selection_keeps_a_positive_near():
  center = np.zeros(3, np.float32)
  cameras = camera.Cameras.create(camera.look_at(np.array([[0.1, 0, 0]], np.float32), center),
                                  fx=10.0, width=4, height=4)
  near, far = control_depth.selection_depth_range(cameras, center, 1.0)
  assert 0 < float(near[0]) < float(far[0])
  assert float(near[0]) == np.float32(0.05) * float(far[0])


def test_control_image_has_three_equal_channels():
  image = np.asarray(control_depth.control_image(np.random.rand(2, 5, 6)))
  assert image.shape == (2, 5, 6, 3)
  np.testing.assert_array_equal(image[..., 0], image[..., 2])
