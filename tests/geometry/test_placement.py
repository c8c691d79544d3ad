"""The support plane under a picked pixel: recovered from noisy surface points despite outliers
(the window reaching onto an object or the background), oriented towards the camera."""

import numpy as np
import pytest

from signerf_jax.errors import InputError
from signerf_jax.geometry import placement


def tilted_plane_points(count: int, rng, noise: float = 0.002):
  normal = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
  u = np.cross(normal, [1.0, 0.0, 0.0])
  u /= np.linalg.norm(u)
  v = np.cross(normal, u)
  offsets = rng.uniform(-0.3, 0.3, (count, 2))
  points = (np.array([0.1, 0.2, 0.3]) + offsets[:, :1] * u + offsets[:, 1:] * v
            + noise * rng.standard_normal((count, 1)) * normal)
  return points, normal


@pytest.mark.parametrize("outlier_share", [0.0, 0.3, 0.45])
def test_a_plane_is_recovered_despite_outliers(outlier_share):
  rng = np.random.default_rng(0)
  points, normal = tilted_plane_points(200, rng)
  count = int(outlier_share * len(points))
  points[:count] += rng.uniform(0.05, 0.4, (count, 1)) * normal  # An object standing on it.
  picked = np.array([0.1, 0.2, 0.3]) + 0.01 * normal
  plane = placement.fit_plane(points, picked, threshold=0.01)
  assert abs(abs(plane.normal @ normal) - 1) < 1e-3  # Within ~2.5 degrees.
  np.testing.assert_allclose(plane.point, [0.1, 0.2, 0.3], atol=0.005)
  assert plane.inlier_fraction == pytest.approx(1 - outlier_share, abs=0.03)
  assert plane.rms_distance < 0.005


def test_the_fit_is_deterministic_in_its_seed():
  points, _ = tilted_plane_points(50, np.random.default_rng(1), noise=0.02)
  first = placement.fit_plane(points, points[0], 0.01, seed=3)
  second = placement.fit_plane(points, points[0], 0.01, seed=3)
  np.testing.assert_array_equal(first.normal, second.normal)


def test_the_normal_is_turned_towards_the_camera():
  plane = placement.Plane(np.zeros(3), np.array([0.0, 0.0, -1.0]), 1.0, 0.0)
  assert placement.orient(plane, [0.0, 1.0, 2.0]).normal.tolist() == [0.0, 0.0, 1.0]
  assert placement.orient(plane, [0.0, 1.0, -2.0]) is plane


@pytest.mark.parametrize("points", [np.zeros((2, 3)), np.full((10, 3), np.nan),
                                    np.outer(np.arange(10.0), [1.0, 2.0, 3.0])],
                         ids=["two_points", "not_finite", "collinear"])
def test_too_little_surface_is_an_error_naming_the_pixel(points):
  with pytest.raises(InputError) as error:
    placement.fit_plane(points, np.zeros(3), 0.01)
  assert error.value.field == "pixel"


def test_the_window_starts_with_the_picked_pixel_and_stays_inside_the_image():
  xs, ys = placement.window_pixels(0.7, 9.2, width=12, height=10, radius=2)
  assert (xs[0], ys[0]) == (np.float32(0.7), np.float32(9.2))
  assert xs[1:].min() == 0.5 and xs[1:].max() == 2.5 and ys[1:].min() == 7.5
  assert ys[1:].max() == 9.5 and len(xs) == 1 + 3 * 3
