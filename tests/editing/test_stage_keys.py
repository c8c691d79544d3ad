"""Stage keys: settings added after edits were first keyed leave those edits' keys as they were."""

import dataclasses

import pytest

from signerf_jax.editing import config
from signerf_jax.nerf.train import TrainConfig


def test_an_edit_keys_its_trainings_without_the_sparse_priors_at_their_defaults():
  # Edits keyed before these settings existed keep their trained NeRFs.
  key = config.training_key(TrainConfig())
  assert not set(config.LATER_TRAINING_FIELDS) & set(key)
  assert set(key) | set(config.LATER_TRAINING_FIELDS) == {
      field.name for field in dataclasses.fields(TrainConfig)}
  assert config.training_key(TrainConfig(keypoint_depth_weight=0.0))[
      "keypoint_depth_weight"] == 0.0


@pytest.mark.parametrize("name, keyed_as, given", [
    ("distortion_loss_weight", 0.002, 0.01),
    ("learning_rate", 1e-2, 5e-3),
    ("final_learning_rate", 1e-3, 5e-4),
])
def test_the_settings_left_to_the_capture_are_keyed_as_they_were(name, keyed_as, given):
  assert config.training_key(TrainConfig())[name] == keyed_as
  assert config.training_key(TrainConfig(**{name: given}))[name] == given
