"""Small in-memory datasets for the data-layer tests."""

from __future__ import annotations

import numpy as np
import pytest

from signerf_jax import camera
from signerf_jax.data import Dataset


def make_dataset(count: int = 5, width: int = 12, height: int = 9, *, distortion=None,
                 fisheye: bool = False, per_frame_intrinsics: bool = False,
                 with_extras: bool = True, world_from_source=None, seed: int = 0) -> Dataset:
  """Cameras on a ring looking at the origin, random images; optional masks/depths/object ids."""
  rng = np.random.default_rng(seed)
  angles = np.linspace(0, 2 * np.pi, count, endpoint=False)
  eyes = np.stack([2.5 * np.cos(angles), 2.5 * np.sin(angles), np.full(count, 0.8)], -1)
  camera_to_world = np.asarray(camera.look_at(eyes.astype(np.float32), np.zeros(3, np.float32)))
  focal = 10.0 + (rng.uniform(0, 2, count) if per_frame_intrinsics else 0.0)
  cameras = camera.Cameras.create(camera_to_world, fx=focal, fy=focal * 1.05,
                                  cx=width / 2 + 0.25, cy=height / 2 - 0.5, width=width,
                                  height=height, distortion=distortion, fisheye=fisheye)
  shape = (count, height, width)
  return Dataset(
      images=rng.uniform(0, 1, shape + (3,)).astype(np.float32),
      cameras=cameras,
      image_names=tuple(f"view_{index}.png" for index in range(count)),
      scene_bounds=np.array([[-0.8, -0.8, -0.5], [0.8, 0.8, 0.6]], np.float32),
      scene_kind="bounded", near=1.5, far=3.5,
      background_color=np.array([1.0, 0.5, 0.0], np.float32),
      world_from_source=(np.eye(4, dtype=np.float32) if world_from_source is None
                         else np.asarray(world_from_source, np.float32)),
      masks=(rng.uniform(0, 1, shape) > 0.3).astype(np.float32) if with_extras else None,
      depths=rng.uniform(1, 4, shape).astype(np.float32) if with_extras else None,
      extras={"object_masks": rng.integers(0, 4, shape).astype(np.int32)} if with_extras else {},
  )


@pytest.fixture
def dataset_factory():
  """`make_dataset` (fixtures are how test modules without packages share helpers)."""
  return make_dataset
