import jax
import jax.numpy as jnp
import numpy as np
import pytest

from signerf_jax.nerf import volume

DENSITIES = [0.0, 1e-10, 1e-5, 1.0, 1e5, 1e10]


def render_and_gradient(densities, edges, rgbs=None, background=(0.2, 0.4, 0.6)):
  densities = jnp.asarray(densities, jnp.float32)
  edges = jnp.asarray(edges, jnp.float32)
  rgbs = jnp.full(densities.shape + (3,), 0.5) if rgbs is None else jnp.asarray(rgbs)
  background = jnp.asarray(background, jnp.float32)

  def scalar_outputs(densities, rgbs):
    out = volume.volume_render(densities, rgbs, edges, jnp.ones(densities.shape[:-1]), background)
    return sum(jnp.sum(out[name]) for name in ("rgb", "accumulation", "distance", "depth"))

  outputs = volume.volume_render(densities, rgbs, edges, jnp.ones(densities.shape[:-1]),
                                 background)
  gradients = jax.grad(scalar_outputs, argnums=(0, 1))(densities, rgbs)
  return outputs, gradients


def assert_all_finite(outputs, gradients):
  for name, value in outputs.items():
    assert np.all(np.isfinite(value)), name
  for gradient in gradients:
    assert np.all(np.isfinite(gradient))


@pytest.mark.parametrize("density", DENSITIES)
@pytest.mark.parametrize("last_edge", [3.0, 1e10, np.inf])
def test_finite_for_any_density_and_far_or_infinite_last_interval(density, last_edge):
  edges = [1.0, 1.5, 2.0, 2.5, last_edge]
  outputs, gradients = render_and_gradient(np.full(4, density), edges)
  assert_all_finite(outputs, gradients)
  weights = outputs["weights"]
  assert np.all(weights >= 0) and float(jnp.sum(weights)) <= 1 + 1e-6
  expected_opacity = 1 - np.exp(-density * (min(last_edge, 1e10) - 1.0))
  assert float(outputs["accumulation"]) == pytest.approx(min(expected_opacity, 1.0), abs=1e-5)


@pytest.mark.parametrize("density", DENSITIES)
def test_zero_length_intervals_contribute_nothing(density):
  edges = [2.0, 2.0, 2.0, 2.0]
  outputs, gradients = render_and_gradient(np.full(3, density), edges)
  assert_all_finite(outputs, gradients)
  assert float(outputs["accumulation"]) == 0.0
  np.testing.assert_allclose(outputs["rgb"], [0.2, 0.4, 0.6], atol=1e-6)


def test_all_empty_ray_shows_background_at_far_depth():
  outputs, gradients = render_and_gradient(np.zeros(8), np.linspace(1, 3, 9))
  assert_all_finite(outputs, gradients)
  np.testing.assert_allclose(outputs["rgb"], [0.2, 0.4, 0.6], atol=1e-6)
  assert float(outputs["distance"]) == pytest.approx(3.0)
  assert float(outputs["median_distance"]) == pytest.approx(3.0)


@pytest.mark.parametrize("opaque_index", [0, 3, 7])
def test_single_opaque_sample_gives_one_hot_weights(opaque_index):
  densities = np.zeros(8)
  densities[opaque_index] = 1e10
  edges = np.linspace(1, 3, 9)
  colours = np.zeros((8, 3))
  colours[opaque_index] = [1.0, 0.0, 0.5]
  outputs, gradients = render_and_gradient(densities, edges, colours)
  assert_all_finite(outputs, gradients)
  np.testing.assert_allclose(outputs["weights"], np.eye(8)[opaque_index], atol=1e-6)
  np.testing.assert_allclose(outputs["rgb"], [1.0, 0.0, 0.5], atol=1e-6)
  centre = 0.5 * (edges[opaque_index] + edges[opaque_index + 1])
  assert float(outputs["distance"]) == pytest.approx(centre, abs=1e-5)
  assert float(outputs["median_distance"]) == pytest.approx(centre, abs=1e-5)


def test_matches_closed_form_and_depth_uses_cosine():
  densities = jnp.array([[0.5, 2.0, 0.0, 3.0]])
  edges = jnp.array([[1.0, 1.2, 1.5, 1.6, 2.0]])
  colours = jnp.broadcast_to(jnp.array([0.1, 0.5, 0.9, 0.3])[:, None], (1, 4, 3))
  cos = jnp.array([0.8])
  outputs = volume.volume_render(densities, colours, edges, cos, None)
  deltas = np.diff(np.asarray(edges[0]))
  tau = np.asarray(densities[0]) * deltas
  transmittance = np.exp(-np.concatenate([[0], np.cumsum(tau)[:-1]]))
  weights = transmittance * (1 - np.exp(-tau))
  np.testing.assert_allclose(outputs["weights"][0], weights, rtol=1e-5)
  centres = 0.5 * (np.asarray(edges[0, 1:]) + np.asarray(edges[0, :-1]))
  distance = np.sum(weights * centres) / np.sum(weights)
  assert float(outputs["distance"][0]) == pytest.approx(distance, rel=1e-5)
  assert float(outputs["depth"][0]) == pytest.approx(0.8 * distance, rel=1e-5)
  np.testing.assert_allclose(outputs["rgb"][0, 0], np.sum(weights * [0.1, 0.5, 0.9, 0.3]),
                             rtol=1e-5)


def test_gradient_of_colour_with_respect_to_density_is_exact():
  densities = jnp.array([0.3, 1.2, 0.7])
  edges = jnp.array([0.0, 0.5, 1.0, 2.0])
  colours = jnp.array([[1.0] * 3, [0.0] * 3, [0.5] * 3])

  def red(densities):
    return volume.volume_render(densities, colours, edges, jnp.ones(()), None)["rgb"][0]

  analytic = jax.grad(red)(densities)
  step = 1e-3
  numeric = [(red(densities.at[i].add(step)) - red(densities.at[i].add(-step))) / (2 * step)
             for i in range(3)]
  np.testing.assert_allclose(analytic, numeric, rtol=1e-2, atol=1e-4)
