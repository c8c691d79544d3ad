"""Selections are given in the dataset's own world units and mapped into the NeRF's frame."""

import numpy as np

from signerf_jax.data import poses
from signerf_jax.editing import config as config_lib
from signerf_jax.editing import select
from tests.data.conftest import make_dataset

# Source -> scene: halve, turn 90 degrees about z, shift.
ROTATION = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
WORLD_FROM_SOURCE = poses.similarity(0.5, ROTATION, np.array([0.1, -0.2, 0.05]))


def _dataset():
  return make_dataset(world_from_source=WORLD_FROM_SOURCE, with_extras=False)


def test_a_box_in_source_units_is_the_same_place_in_the_scene_frame():
  dataset = _dataset()
  assert config_lib.SelectionConfig(kind="proxy", proxy="primitive:box").frame == "source"
  lower, upper = np.array([-0.4, -0.2, -0.6]), np.array([0.2, 0.6, 0.2])
  box = select.make_box(config_lib.SelectionConfig(box_min=tuple(lower), box_max=tuple(upper)),
                        dataset)
  corners = poses.transform_points(WORLD_FROM_SOURCE, np.stack([lower, upper]))
  np.testing.assert_allclose(box.minimum, corners.min(0), atol=1e-6)
  np.testing.assert_allclose(box.maximum, corners.max(0), atol=1e-6)
  in_scene = select.make_box(config_lib.SelectionConfig(
      box_min=tuple(lower), box_max=tuple(upper), frame="scene"), dataset)
  np.testing.assert_allclose(in_scene.minimum, lower, atol=1e-6)


def test_a_proxy_on_the_ground_in_source_units_lands_where_the_source_says():
  dataset = _dataset()
  position = np.array([0.3, -0.1, 0.2])
  placed = select.place_proxy(config_lib.SelectionConfig(
      kind="proxy", proxy="primitive:sphere", ground_position=tuple(position), ground_size=0.4),
      dataset)
  # Up (the cameras' mean up, here scene +z) in source units is R^T z; the footprint centre is
  # `position`, so the lowest point along up is the position mapped into the scene frame.
  scene_up = np.array([0.0, 0.0, 1.0])
  vertices = np.asarray(placed.vertices, np.float64)
  lowest = vertices[np.argmin(vertices @ scene_up)]
  expected = poses.transform_points(WORLD_FROM_SOURCE, position[None])[0]
  np.testing.assert_allclose(lowest @ scene_up, expected @ scene_up, atol=1e-5)
  # The proxy is 0.4 source units across, 0.2 scene units.
  extent = vertices.max(0) - vertices.min(0)
  np.testing.assert_allclose(extent.max(), 0.2, rtol=1e-4)
