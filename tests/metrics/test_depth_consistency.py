"""Multi-view depth consistency: exact depths of a scene agree between views; floaters, fog and
transparent pixels are told apart; bad input names its field."""

from __future__ import annotations

import numpy as np
import pytest

from signerf_jax import camera as camera_lib
from signerf_jax.errors import InputError
from signerf_jax.metrics import depth_consistency

SIZE = 48


def _cameras(distortion=None) -> camera_lib.Cameras:
  """Three cameras 4 units above the ground plane z = 0, a little apart, looking at the origin;
  camera 2 is farthest from the others."""
  eyes = np.array([[0.0, -1.0, 4.0], [0.3, -1.0, 4.0], [2.0, -1.5, 3.5]], np.float32)
  camera_to_world = np.asarray(camera_lib.look_at(eyes, np.zeros_like(eyes)))
  return camera_lib.Cameras.create(camera_to_world, 40.0, width=SIZE, height=SIZE,
                                   distortion=distortion)


def _plane_depths(cameras: camera_lib.Cameras) -> np.ndarray:
  """[N, H, W] exact z-depth of the ground plane z = 0 (a render of a perfect surface)."""
  depths = []
  for index in range(cameras.num_cameras):
    rays = camera_lib.image_rays(cameras, index)
    origins, directions = np.asarray(rays.origins), np.asarray(rays.directions)
    distance = -origins[..., 2] / directions[..., 2]
    depths.append(distance * np.asarray(rays.cos_to_optical_axis))
  return np.stack(depths).astype(np.float32)


@pytest.mark.parametrize("distortion", [None, (-0.12, 0.03, 0.001, -0.002)],
                         ids=["pinhole", "distorted lens"])
def test_exact_depths_of_a_surface_agree_between_views(distortion):
  cameras = _cameras(distortion)
  depths = _plane_depths(cameras)
  report = depth_consistency.depth_consistency(cameras, depths, np.ones_like(depths))
  assert report["neighbours"] == [1, 0, 1]
  # Views 0 and 1 share about nine tenths of their frames; view 2 sees ground view 1 does not.
  assert report["per_view"][0] > 0.85 and report["per_view"][1] > 0.85
  assert report["consistent_fraction"] > 0.75
  assert report["surface_fraction"] == 1.0


def test_a_floater_in_front_of_the_surface_is_inconsistent():
  cameras = _cameras()
  depths = _plane_depths(cameras)
  clean = depth_consistency.depth_consistency(cameras, depths, np.ones_like(depths))
  floater = depths.copy()
  floater[0, 10:30, 10:30] *= 0.5  # Something half-way to the camera, in view 0 only.
  report = depth_consistency.depth_consistency(cameras, floater, np.ones_like(depths))
  lost = clean["per_view"][0] - report["per_view"][0]
  # Every floater pixel fails (400 of 2,304), and view 1's pixels that land on it too.
  assert lost == pytest.approx(400 / SIZE**2, abs=0.02)
  assert report["per_view"][1] < clean["per_view"][1] - 0.1


def test_fog_like_depth_noise_is_inconsistent():
  cameras = _cameras()
  depths = _plane_depths(cameras)
  noisy = depths * np.random.default_rng(0).uniform(0.9, 1.1, depths.shape).astype(np.float32)
  report = depth_consistency.depth_consistency(cameras, noisy, np.ones_like(depths))
  assert report["consistent_fraction"] < 0.25


def test_transparent_pixels_are_not_checked_and_fail_where_a_neighbour_lands():
  cameras = _cameras()
  depths = _plane_depths(cameras)
  opacities = np.ones_like(depths)
  opacities[0] = 0.0
  report = depth_consistency.depth_consistency(cameras, depths, opacities)
  assert report["per_view"][0] is None
  assert report["per_view"][1] == 0.0  # Its neighbour (view 0) has no surface anywhere.
  assert report["surface_fraction"] == pytest.approx(2 / 3)
  empty = depth_consistency.depth_consistency(cameras, depths, np.zeros_like(depths))
  assert empty["consistent_fraction"] == 0.0 and empty["per_view"] == [None] * 3


@pytest.mark.parametrize("bad", [np.inf, np.nan, 0.0, -1.0])
def test_invalid_depths_are_not_surfaces(bad):
  cameras = _cameras()
  depths = _plane_depths(cameras)
  depths[0, :, :SIZE // 2] = bad
  report = depth_consistency.depth_consistency(cameras, depths, np.ones_like(depths))
  assert report["surface_fraction"] == pytest.approx(1 - 1 / 6)
  assert 0.0 < report["per_view"][0] <= 1.0


def test_bad_input_names_its_field_and_a_second_call_does_not_recompile():
  cameras = _cameras()
  depths = _plane_depths(cameras)
  with pytest.raises(InputError, match="depths"):
    depth_consistency.depth_consistency(cameras, depths[:, :-1], np.ones_like(depths))
  with pytest.raises(InputError, match="opacities"):
    depth_consistency.depth_consistency(cameras, depths, np.ones((3, SIZE)))
  with pytest.raises(InputError, match="at least 2 views"):
    depth_consistency.nearest_views(cameras.take([0]))
  depth_consistency.depth_consistency(cameras, depths, np.ones_like(depths))
  compiled = depth_consistency._consistent_pixels._cache_size()  # pylint: disable=protected-access
  depth_consistency.depth_consistency(cameras, depths * 1.5, np.ones_like(depths))
  assert depth_consistency._consistent_pixels._cache_size() == compiled  # pylint: disable=protected-access
