"""Fixtures of the pipeline tests: a random-weight diffusers pipeline and a tiny scene."""

from __future__ import annotations

import pytest

from signerf_jax.data import synthetic, synthetic_render

from random_pipeline import write_random_pipeline


@pytest.fixture(scope="session")
def random_model(tmp_path_factory):
  """A random-weight ControlNet inpainting pipeline in diffusers layout (latent factor 2)."""
  return write_random_pipeline(tmp_path_factory.mktemp("random_model"))


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory):
  """A 40-pixel synthetic scene, 12 views on a hemisphere, two primitives and a free spot.

  The narrow field of view keeps the scene's corners out of some views (empty masks there).
  """
  directory = tmp_path_factory.mktemp("tiny_scene")
  _, scene = synthetic_render.generate(
      directory, seed=2, settings=synthetic.SceneSettings(num_primitives=2, num_meshes=0),
      rig=synthetic_render.CameraRig(num_views=12, image_size=40, field_of_view_degrees=40.0))
  return directory, scene
