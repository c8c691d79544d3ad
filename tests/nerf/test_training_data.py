"""A training step's batch: each pixel's rays (one, or pixel_samples^2 through a grid inside it)
come together, in the pixels' order, with that pixel's target colour and random background."""

import dataclasses

import jax
import numpy as np
import pytest

from signerf_jax import camera
from signerf_jax.nerf import training_data

from small_nerf import small_model

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("per_side", [1, 2, 3])
def test_a_steps_rays_split_into_the_sample_groups_whatever_the_rays_a_pixel(sphere, per_side):
  capacity = dataclasses.replace(small_model(sphere).capacity, rays_per_batch=8192,
                                 sample_groups=8)
  pixels = training_data.pixels_per_step(capacity, per_side)
  assert pixels * per_side**2 % 8 == 0
  assert 8192 - 8 * per_side**2 < pixels * per_side**2 <= 8192  # The fewest rays dropped.


@pytest.mark.parametrize("per_side", [1, 2, 3])
def test_each_pixels_rays_cross_that_pixel_and_share_its_target_and_background(sphere, per_side):
  alphas = np.ones(sphere.images.shape[:3], np.float32)
  alphas[:, :, :5] = 0.0  # A transparent strip: its targets take the random background.
  dataset = dataclasses.replace(sphere, alphas=alphas)
  model = small_model(dataset)
  model = dataclasses.replace(model, capacity=dataclasses.replace(
      model.capacity, pixel_samples=per_side, rays_per_batch=288))
  data = training_data.TrainingData.from_dataset(dataset)
  rays, target, weight, background, surroundings, rays_per_pixel = jax.jit(
      training_data.step_batch, static_argnums=0)(model, data, jax.random.PRNGKey(1),
                                                  jax.random.PRNGKey(2))
  pixels = 288 // per_side**2
  assert rays_per_pixel == per_side**2 and surroundings is None
  assert rays.shape == (288,) and target.shape == (pixels, 3) and weight.shape == (pixels,)
  assert background.shape == (288, 3)
  # Where each ray crosses the image plane: inside one pixel, the same for a pixel's rays.
  index = np.asarray(rays.camera_indices)
  projected = np.stack([np.asarray(camera.project(dataset.cameras.take([view]),
                                                  origin + direction)[0][0])
                        for view, origin, direction in zip(index, np.asarray(rays.origins),
                                                           np.asarray(rays.directions))])
  column, row = np.floor(projected).astype(int).T
  fraction = projected - np.floor(projected)
  assert np.all(np.abs(fraction - 0.5) < 0.5 - 0.5 / per_side + 1e-3)  # Off the pixel's edges.
  grouped = lambda array: np.asarray(array).reshape(pixels, per_side**2, *np.shape(array)[1:])
  for values in (index, row, column, background):
    assert np.all(grouped(values) == grouped(values)[:, :1])
  first = (index[::per_side**2], row[::per_side**2], column[::per_side**2])
  transparency = 1.0 - alphas[first][:, None]
  expected = (dataset.images[first]
              + transparency * (np.asarray(background)[::per_side**2] - model.background))
  np.testing.assert_allclose(target, expected, atol=1e-6)
  assert transparency.any() and not transparency.all()
