"""The support plane under a picked pixel: recovered from noisy surface points despite outliers
(the window reaching onto an object or the background), oriented towards the camera."""

import numpy as np
import pytest

from signerf_jax import camera
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


def two_views_of(corners):
  """Two cameras 90 degrees apart looking at the origin, and each one's pixel rectangle around
  the projected `corners`."""
  eyes = np.array([[3.0, 0.0, 0.5], [0.0, -3.0, 0.5]], np.float32)
  cameras = camera.Cameras.create(np.asarray(camera.look_at(eyes, np.zeros(3, np.float32))),
                                  fx=60.0, width=64, height=64)
  pixels, _ = camera.project(cameras, corners)
  pixels = np.asarray(pixels)
  return cameras, np.concatenate([pixels.min(1), pixels.max(1)], axis=1)


def test_rectangles_in_two_views_triangulate_the_box_around_the_object():
  lower, upper = np.array([-0.2, 0.1, 0.0]), np.array([0.3, 0.4, 0.5])
  corners = np.stack(np.meshgrid(*np.stack([lower, upper]).T, indexing="ij"), -1).reshape(-1, 3)
  cameras, rectangles = two_views_of(corners)
  box = placement.frusta_box(cameras, rectangles, [[-1, -1, -1], [1, 1, 1]])
  assert np.all(box[0] <= lower + 1e-6) and np.all(box[1] >= upper - 1e-6)  # Contains it,
  assert np.all(box[0] >= lower - 0.25) and np.all(box[1] <= upper + 0.25)  # and little more.


@pytest.mark.parametrize("rectangles", [[[10, 10, 20, 20]], [[10, 10, 10, 20], [5, 5, 9, 9]],
                                        [[0, 0, 3, 3], [60, 60, 64, 64]]],
                         ids=["one_view", "no_area", "frusta_do_not_meet"])
def test_rectangles_that_do_not_triangulate_are_errors(rectangles):
  cameras, _ = two_views_of(np.zeros((1, 3)))
  cameras = cameras.take(np.arange(len(rectangles)))
  with pytest.raises(InputError) as error:
    placement.frusta_box(cameras, rectangles, [[-1, -1, -1], [1, 1, 1]])
  assert error.value.field == "rectangle"
