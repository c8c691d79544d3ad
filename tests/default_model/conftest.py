"""Small, fast settings for the default model's data tests (primitives only, 32-pixel views)."""

from __future__ import annotations

import pytest

from signerf_jax.default_model import samples


@pytest.fixture(scope="session")
def tiny_sampling(tmp_path_factory) -> samples.SceneSampling:
  """32-pixel views, a 12-camera rig and no shared meshes (an empty mesh directory)."""
  return samples.SceneSampling(image_size=32, rig_views=12, min_object_pixels=8,
                               mesh_directory=str(tmp_path_factory.mktemp("no_meshes")))
