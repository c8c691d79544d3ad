"""Continuing the default model's training from an exported model (`stages.train(initial=...)`,
`train_default_model.py --init_from`): every stage starts from the export instead of its random
initialisation, and an export of another architecture is refused, naming the component."""

import dataclasses

import jax
import numpy as np
import pytest

from signerf_jax.default_model import export, stage_settings, stages, training
from signerf_jax.errors import InputError

pytestmark = pytest.mark.slow

# No steps: what a stage returns is exactly what it started from (and nothing compiles).
STARTS_ONLY = stages.TrainingPlan(
    seed=1, vae=stage_settings.VaeStage(num_steps=0, scaling_views=16),
    unet=stage_settings.UNetStage(num_steps=0),
    controlnet=stage_settings.ControlNetStage(num_steps=0))
BUDGET = training.RunBudget(progress=False)


@pytest.fixture(scope="module")
def exported(tiny_architecture, tiny_training_data, tmp_path_factory):
  """A tiny model's parameters (seed 0) and the directory they were exported to (float32)."""
  directory = tmp_path_factory.mktemp("continue")
  trained = stages.train(directory / "run", tiny_training_data, tiny_architecture, BUDGET,
                         dataclasses.replace(STARTS_ONLY, seed=0))
  export.write_checkpoint(directory / "weights", trained.architecture, trained.params,
                          tiny_training_data.tokenizer, dtype=np.float32)
  return trained.params, directory / "weights"


def test_every_stage_starts_from_the_exported_model(exported, tiny_architecture,
                                                    tiny_training_data, tmp_path):
  params, weights = exported
  continued = stages.train(tmp_path / "run", tiny_training_data, tiny_architecture, BUDGET,
                           STARTS_ONLY, initial=export.initial_params(weights))
  fresh = stages.train(tmp_path / "fresh", tiny_training_data, tiny_architecture, BUDGET,
                       STARTS_ONLY)
  for name in ("vae", "unet", "text_encoder", "controlnet"):
    jax.tree.map(np.testing.assert_array_equal, continued.params[name], params[name])
    assert not all(jax.tree.leaves(jax.tree.map(np.array_equal, fresh.params[name],
                                                params[name]))), name


def test_an_export_of_another_architecture_is_an_input_error(exported, tiny_architecture,
                                                             tiny_training_data, tmp_path):
  wider = dataclasses.replace(tiny_architecture, unet_block_out_channels=(16, 48))
  with pytest.raises(InputError, match="unet parameters do not fit"):
    stages.train(tmp_path / "run", tiny_training_data, wider, BUDGET, STARTS_ONLY,
                 initial=export.initial_params(exported[1]))
