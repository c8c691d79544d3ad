"""Sample colour agreement with neighbouring views (`nerf.photo_consistency`): two cameras see
a textured plane; a ray's weight at the plane costs least, more the further it lies off it;
samples neither neighbour sees cost nothing; the gradient moves weight towards the plane and is
finite on the hard cases; the loss is part of a training step when asked for, and a sparse
capture with a background trains with its views' neighbours."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from small_nerf import SMALL_CONFIG, small_model

from signerf_jax import camera
from signerf_jax.nerf import photo_consistency, train, training_data, training_run

SIZE = 32
SAMPLES = 32
TRUNCATION = 0.25


def texture(x, y):
  """A smooth colour texture on the plane z = 0 (varies within a few pixels of these views)."""
  return jnp.stack([0.5 + 0.5 * jnp.sin(7 * x), 0.5 + 0.5 * jnp.cos(5 * y),
                    0.5 + 0.5 * jnp.sin(3 * x + 4 * y)], axis=-1)


@pytest.fixture(scope="module")
def plane_views():
  """Two cameras 0.5 apart at z = 2 looking down at the plane z = 0, and their images."""
  eyes = [(-0.25, 0.0, 2.0), (0.25, 0.0, 2.0)]
  camera_to_world = jnp.stack([camera.look_at(jnp.array(eye), jnp.array((eye[0], 0.0, 0.0)),
                                              up=(0.0, 1.0, 0.0)) for eye in eyes])
  cameras = camera.Cameras.create(camera_to_world, 40.0, width=SIZE, height=SIZE)
  images = []
  for index in range(2):
    rays = camera.image_rays(cameras, index)
    distance = -rays.origins[..., 2] / rays.directions[..., 2]
    points = rays.origins + distance[..., None] * rays.directions
    images.append(texture(points[..., 0], points[..., 1]))
  return cameras, jnp.stack(images)


def first_view_rays(cameras):
  """The first camera's rays [R], interval edges [R, S + 1] from 1 to 3 and the interval
  holding the plane [R]."""
  rays = camera.image_rays(cameras, 0).reshape(-1)
  distance = -rays.origins[:, 2] / rays.directions[:, 2]
  edges = jnp.broadcast_to(jnp.linspace(1.0, 3.0, SAMPLES + 1), (rays.shape[0], SAMPLES + 1))
  midpoints = (edges[:, 1:] + edges[:, :-1]) / 2
  return rays, edges, jnp.argmin(jnp.abs(midpoints - distance[:, None]), axis=1)


def disagreement(plane_views, weights, edges=None):
  cameras, images = plane_views
  rays, default_edges, _ = first_view_rays(cameras)
  views = photo_consistency.neighbour_views(cameras, 1)
  return photo_consistency.sample_disagreement(
      default_edges if edges is None else edges, weights, rays, images, cameras, views,
      jnp.ones(rays.shape[0]), TRUNCATION)


def test_weight_on_the_surface_disagrees_least_and_more_the_further_off(plane_views):
  _, _, surface = first_view_rays(plane_views[0])
  costs = [float(disagreement(plane_views, 0.9 * jax.nn.one_hot(
      jnp.clip(surface + offset, 0, SAMPLES - 1), SAMPLES)))
           for offset in (-6, -3, 0, 3, 6)]
  assert costs[2] < 0.01
  assert costs[1] > 2 * costs[2] and costs[3] > 2 * costs[2]
  assert costs[0] > costs[1] and costs[4] > costs[3]
  assert max(costs) <= TRUNCATION


def test_the_gradient_moves_weight_towards_the_surface(plane_views):
  _, _, surface = first_view_rays(plane_views[0])
  uniform = jnp.full((SIZE * SIZE, SAMPLES), 0.9 / SAMPLES)
  gradient = jax.grad(lambda weights: disagreement(plane_views, weights))(uniform)
  at_surface = gradient[jnp.arange(SIZE * SIZE), surface]
  seen = jnp.any(gradient != 0, axis=1)  # rays the other camera sees some of
  assert float(jnp.mean(seen)) > 0.5
  lower = at_surface < jnp.mean(gradient, axis=1)
  assert float(jnp.sum(lower & seen) / jnp.sum(seen)) > 0.9


@pytest.mark.parametrize("case", ["zero_weights", "huge_weights", "infinite_last_edge",
                                  "behind_every_camera"])
def test_hard_cases_give_finite_values_and_gradients(plane_views, case):
  cameras, _ = plane_views
  rays, edges, _ = first_view_rays(cameras)
  weights = jnp.full((rays.shape[0], SAMPLES), 0.9 / SAMPLES)
  if case == "zero_weights":
    weights = jnp.zeros_like(weights)
  elif case == "huge_weights":
    weights = weights * 1e6
  elif case == "infinite_last_edge":
    edges = edges.at[:, -1].set(jnp.inf)
  else:  # every sample behind the cameras' plane: no neighbour sees any
    edges = -edges[:, ::-1]
  value, gradient = jax.value_and_grad(lambda w: disagreement(plane_views, w, edges))(weights)
  assert np.isfinite(float(value)) and bool(jnp.all(jnp.isfinite(gradient)))
  if case in ("zero_weights", "behind_every_camera"):
    assert float(value) == 0.0


def test_a_second_call_does_not_recompile(plane_views):
  cameras, images = plane_views
  rays, edges, _ = first_view_rays(cameras)
  views = photo_consistency.neighbour_views(cameras, 1)
  jitted = jax.jit(photo_consistency.sample_disagreement, static_argnums=7)
  weights = jnp.full((rays.shape[0], SAMPLES), 0.5 / SAMPLES)
  for scale in (1.0, 2.0):
    jitted(edges, weights * scale, rays, images, cameras, views, jnp.ones(rays.shape[0]),
           TRUNCATION)
  assert jitted._cache_size() == 1


def test_the_disagreement_is_part_of_a_training_step_when_asked_for(sphere):
  model = small_model(sphere)
  config = dataclasses.replace(SMALL_CONFIG, photo_consistency_weight=2.0)
  data = training_data.TrainingData.from_dataset(sphere).replace(
      neighbour_views=photo_consistency.neighbour_views(sphere.cameras, 2))
  state = train.init_state(model, config)
  step = jax.jit(train.train_step, static_argnums=(0, 1))
  new_state, statistics = step(model, config, state, data, np.float32(0.5))
  disagreement = float(statistics["photo_consistency"])
  assert 0 < disagreement <= config.photo_consistency_truncation
  mse = 10 ** (-float(statistics["psnr"]) / 10)
  assert float(statistics["loss"]) >= mse + 2.0 * disagreement - 1e-6
  assert all(np.all(np.isfinite(leaf)) for leaf in jax.tree.leaves(new_state.variables))
  _, without = step(model, SMALL_CONFIG, state, data, np.float32(0.5))
  assert "photo_consistency" not in without


def test_a_sparse_capture_with_a_background_trains_with_its_nearest_views(sphere):
  # The capture's choice itself: tests/nerf/test_capture_choices.py.
  on_constant = training_run.build_model(sphere)
  model = dataclasses.replace(on_constant, capacity=dataclasses.replace(
      on_constant.capacity, background="last_sample"))  # as a 360-degree capture's
  trainer = training_run.make_trainer(sphere.subset(list(range(12))), model=model)
  assert trainer.data.neighbour_views.shape == (
      12, train.TrainConfig().photo_consistency_neighbours)
  assert training_run.make_trainer(sphere, model=model).data.neighbour_views is None


def test_a_first_sample_at_the_camera_leaves_the_rays_own_colour_as_it_is(plane_views):
  # A zero-length interval at the camera centre projects nowhere; the ray's own colour is
  # still its pixel's.
  cameras, _ = plane_views
  _, edges, surface = first_view_rays(cameras)
  edges = jnp.concatenate([jnp.zeros_like(edges[:, :2]), edges], axis=1)
  weights = 0.9 * jax.nn.one_hot(surface + 2, SAMPLES + 2)
  assert float(disagreement(plane_views, weights, edges)) < 0.01
