"""Small, fast settings for the default model's data tests (primitives only, 32-pixel views)."""

from __future__ import annotations

import pytest

from signerf_jax.default_model import scenes


@pytest.fixture(scope="session")
def tiny_sampling(tmp_path_factory) -> scenes.SceneSampling:
  """32-pixel views, a 12-camera rig and no shared meshes (an empty mesh directory)."""
  return scenes.SceneSampling(image_size=32, rig_views=12, min_object_pixels=8,
                              mesh_directory=str(tmp_path_factory.mktemp("no_meshes")))


# The default model's training tests: a tiny architecture (latent factor 2) and a tiny dataset.
TINY_ARCHITECTURE = dict(
    vae_block_out_channels=(8, 16), vae_norm_groups=4, unet_block_out_channels=(16, 32),
    attention_heads=2, norm_groups=8, conditioning_embedding_channels=(4, 8),
    text_hidden_size=16, text_layers=1, text_heads=2, text_intermediate_size=32)


@pytest.fixture(scope="session")
def tiny_architecture():
  from signerf_jax.default_model import model  # pylint: disable=g-import-not-at-top
  return model.Architecture(**TINY_ARCHITECTURE)


@pytest.fixture(scope="session")
def tiny_training_data(tmp_path_factory, tiny_sampling):
  """A training split of 3 sheets and 6 single views of 32 pixels, loaded in memory."""
  from signerf_jax.default_model import dataset_builder, training_data  # pylint: disable=g-import-not-at-top
  directory = tmp_path_factory.mktemp("tiny_training_data")
  dataset_builder.build_dataset(dataset_builder.DataSettings(
      output_directory=str(directory), num_sheets=3, num_singles=6, num_eval_sheets=1,
      num_eval_singles=1, sheets_per_shard=3, singles_per_shard=6), tiny_sampling, progress=False)
  return training_data.load_split(directory, "train", progress=False)
