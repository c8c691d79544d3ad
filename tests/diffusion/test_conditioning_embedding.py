"""The ControlNet's conditioning embedding: its receptive field, recomputing only the cells a
changed rectangle reaches, and the sampler taking it computed already."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from signerf_jax.diffusion import controlnet as controlnet_lib
from signerf_jax.diffusion import model_configs, pipeline, sampler, weights

from test_sampler import CONTROLNET, small_sheet_arguments


def random_controlnet(embedding_channels):
  config = model_configs.ControlNetConfig.from_dict(
      dict(CONTROLNET, conditioning_embedding_out_channels=embedding_channels))
  module = controlnet_lib.ControlNet(config)
  return module, weights.random_params(module, 3)


@pytest.mark.parametrize("embedding_channels, factor, radius", [
    ((8, 8, 16), 4, 11), ((8, 16), 2, 5)])
def test_a_cell_depends_on_the_pixels_within_the_radius_and_on_no_other(
    embedding_channels, factor, radius):
  module, params = random_controlnet(embedding_channels)
  assert controlnet_lib.conditioning_radius(module.config) == radius
  image = np.random.default_rng(0).random((1, 64, 64, 3)).astype(np.float32)
  embed = lambda x: np.asarray(controlnet_lib.embed_conditioning(module, params, jnp.asarray(x)))
  for row, column in ((30, 33), (0, 63), (17, 1)):
    changed_image = image.copy()
    changed_image[0, row, column] = 1.0 - changed_image[0, row, column]
    changed = np.abs(embed(changed_image) - embed(image)).max(axis=(0, 3)) > 0
    for axis, pixel in ((0, row), (1, column)):
      cells = np.flatnonzero(changed.any(axis=1 - axis))
      first, last = -(-(pixel - radius) // factor), (pixel + radius) // factor
      assert (cells.min(), cells.max()) == (max(first, 0), min(last, 64 // factor - 1))


@pytest.mark.parametrize("region", [(13, 7, 10, 9), (0, 0, 16, 16), (40, 32, 24, 16),
                                    (8, 24, 4, 4), (0, 0, 64, 48)])
def test_recomputing_the_cells_a_rectangle_reaches_gives_the_whole_embedding(region):
  module, params = random_controlnet((8, 8, 16))
  rng = np.random.default_rng(1)
  before = rng.random((1, 64, 48, 3)).astype(np.float32)
  after = np.repeat(before, 2, axis=0)
  top, left, height, width = region
  after[:, top:top + height, left:left + width] = rng.random((2, height, width, 3))
  base = controlnet_lib.embed_conditioning(module, params, jnp.asarray(before))
  whole = np.asarray(controlnet_lib.embed_conditioning(module, params, jnp.asarray(after)))
  reused = np.asarray(controlnet_lib.embed_conditioning_region(module, params, base,
                                                               jnp.asarray(after), region))
  assert np.abs(whole - np.asarray(base)).max() > 1e-2
  np.testing.assert_allclose(reused, whole, rtol=0, atol=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize("guess_mode", [False, True])
def test_the_sampler_given_the_control_embedding_samples_what_it_samples_computing_it(
    guess_mode):
  models, schedule, prompt, time_ids, inputs, noise, guidance = small_sheet_arguments(16, 24)
  settings = sampler.SamplerSettings(guess_mode=guess_mode)
  embedding = pipeline.control_embedding(models, inputs.control)
  assert embedding.shape == (1, 4, 6, models.controlnet.config.block_out_channels[0])
  program = sampler.program(models)
  images = [np.asarray(program(models, schedule, prompt, time_ids, given, noise, guidance,
                               settings=settings))
            for given in (inputs, dataclasses.replace(inputs, control_embedding=embedding))]
  np.testing.assert_allclose(images[1], images[0], rtol=0, atol=1e-5)
  # The embedding is what the ControlNet sees: another one samples another image.
  other = dataclasses.replace(inputs, control_embedding=jnp.zeros_like(embedding))
  assert np.abs(np.asarray(program(models, schedule, prompt, time_ids, other, noise, guidance,
                                   settings=settings)) - images[0]).max() > 1e-3
