import jax
import jax.numpy as jnp
import numpy as np
import pytest

from signerf_jax.nerf import losses, sampling


def brute_force_outer(edges, proposal_edges, proposal_weights):
  """Mass of every proposal interval that overlaps each target interval."""
  result = []
  for start, end in zip(edges[:-1], edges[1:]):
    overlap = (proposal_edges[1:] > start) & (proposal_edges[:-1] < end)
    result.append(np.sum(proposal_weights[overlap]))
  return np.array(result)


def test_outer_weights_match_brute_force():
  rng = np.random.default_rng(0)
  for _ in range(5):
    proposal_edges = np.sort(rng.uniform(0, 10, 9))
    proposal_weights = rng.uniform(0, 1, 8)
    edges = np.sort(rng.uniform(0.5, 9.5, 6))
    np.testing.assert_allclose(
        losses.outer_weights(jnp.asarray(edges), jnp.asarray(proposal_edges),
                             jnp.asarray(proposal_weights)),
        brute_force_outer(edges, proposal_edges, proposal_weights), atol=1e-6)


def test_interlevel_loss_is_zero_when_the_proposal_covers_and_positive_otherwise():
  edges = jnp.linspace(0, 1, 9)[None]
  weights = jnp.array([[0, 0, 0.1, 0.7, 0.2, 0, 0, 0]])
  covering = [(edges, weights)]
  assert float(losses.interlevel_loss(edges, weights, covering, jnp.ones(1))) == pytest.approx(0)
  missing = [(edges, jnp.roll(weights, 3, axis=-1))]
  loss, gradient = jax.value_and_grad(
      lambda w: losses.interlevel_loss(edges, weights, [(edges, w)], jnp.ones(1)))(missing[0][1])
  assert float(loss) > 0.1
  # The proposal is pushed up where the NeRF has mass it does not cover.
  assert float(gradient[0, 3]) < 0
  # A dropped ray (weight 0) contributes nothing.
  assert float(losses.interlevel_loss(edges, weights, missing, jnp.zeros(1))) == 0


def test_weighted_mse_ignores_zero_weight_rays():
  predicted = jnp.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
  target = jnp.zeros((2, 3))
  assert float(losses.weighted_mse(predicted, target, jnp.array([1.0, 0.0]))) == 0.0
  assert float(losses.weighted_mse(predicted, target, jnp.array([1.0, 1.0]))) == pytest.approx(0.5)
  assert np.isfinite(float(losses.weighted_mse(predicted, target, jnp.zeros(2))))


def brute_force_distortion(edges, weights):
  midpoints = 0.5 * (edges[1:] + edges[:-1])
  pairwise = np.sum(weights[:, None] * weights[None, :] *
                    np.abs(midpoints[:, None] - midpoints[None, :]))
  return pairwise + np.sum(weights**2 * np.diff(edges)) / 3


def test_distortion_matches_pairwise_sum_and_prefers_concentrated_weights():
  rng = np.random.default_rng(1)
  edges = np.sort(rng.uniform(0, 4, 9))
  weights = rng.uniform(0, 0.2, 8)
  per_ray = losses.ray_distortion(jnp.asarray(edges)[None], jnp.asarray(weights)[None], 2.0)
  assert float(per_ray[0]) == pytest.approx(brute_force_distortion(edges / 2, weights), rel=1e-5)
  uniform_edges = jnp.linspace(0, 1, 9)[None]
  spread = losses.ray_distortion(uniform_edges, jnp.full((1, 8), 1 / 8), 1.0)
  peaked = losses.ray_distortion(uniform_edges, jnp.eye(8)[3:4], 1.0)
  assert float(peaked[0]) < float(spread[0])


def test_distortion_loss_is_the_weighted_mean_over_rays_and_caps_an_infinite_interval():
  edges = jnp.array([[1.0, 2.0, 3.0, sampling.MAX_DISTANCE], [1.0, 2.0, 3.0, 4.0]])
  weights = jnp.array([[0.0, 0.5, 0.5], [0.2, 0.2, 0.2]])
  loss = losses.distortion_loss({"edges": edges, "weights": weights}, 1.0,
                                jnp.array([1.0, 3.0]))
  # The first ray's infinite last interval ends at twice its start: [3, 6].
  first = brute_force_distortion(np.array([1.0, 2.0, 3.0, 6.0]), np.array([0.0, 0.5, 0.5]))
  second = brute_force_distortion(np.array([1.0, 2.0, 3.0, 4.0]), np.full(3, 0.2))
  assert float(loss) == pytest.approx((first + 3 * second) / 4, rel=1e-5)


def test_gradient_scaling_keeps_values_and_scales_gradients_by_squared_distance():
  densities = jnp.array([[1.0, 1e10, 0.0, 5.0]])
  rgbs = jnp.full((1, 4, 3), 0.5)
  edges = jnp.array([[0.0, 0.2, 0.6, 2.0, sampling.MAX_DISTANCE]])
  distances = sampling.midpoints(edges)
  scaled_densities, scaled_rgbs = losses.near_camera_gradient_scaling(densities, rgbs, distances,
                                                                      1.0)
  np.testing.assert_array_equal(scaled_densities, densities)
  np.testing.assert_array_equal(scaled_rgbs, rgbs)
  gradient = jax.grad(lambda d: jnp.sum(losses.near_camera_gradient_scaling(
      d, rgbs, distances, 1.0)[0]))(densities)
  # Midpoints 0.1, 0.4, 1.3, ~5e9: (t / 1)^2 up to 1.
  np.testing.assert_allclose(gradient, [[0.01, 0.16, 1.0, 1.0]], rtol=1e-6)
  colour_gradient = jax.grad(lambda c: jnp.sum(losses.near_camera_gradient_scaling(
      densities, c, distances, 2.0)[1]))(rgbs)
  np.testing.assert_allclose(colour_gradient[0, :, 0], [0.0025, 0.04, 0.4225, 1.0], rtol=1e-5)
  assert np.all(np.isfinite(colour_gradient))


@pytest.mark.parametrize("opacity, expected", [(0.0, 0.0), (1.0, 0.0), (0.5, np.log(2.0)),
                                               (0.1, -(0.1 * np.log(0.1) + 0.9 * np.log(0.9)))])
def test_opacity_entropy_is_zero_for_empty_and_opaque_rays_and_largest_at_half(opacity,
                                                                               expected):
  weights = jnp.array([[opacity / 2, opacity / 2, 0.0]])
  value = losses.opacity_entropy(weights, jnp.ones(1))
  np.testing.assert_allclose(value, expected, atol=2e-3)


def test_opacity_entropy_gradients_are_finite_and_push_away_from_half():
  weights = jnp.array([[0.0, 0.0], [0.5, 0.5], [0.3, 0.0], [0.4, 0.3], [1e-12, 0.0]])
  gradient = jax.grad(lambda w: losses.opacity_entropy(w, jnp.ones(5)))(weights)
  assert np.all(np.isfinite(gradient))
  assert gradient[3, 0] < 0 < gradient[2, 0]  # descent takes 0.3 towards 0, 0.7 towards 1
  ignored = jax.grad(lambda w: losses.opacity_entropy(w, jnp.array([1.0, 0, 0, 0, 0])))(weights)
  np.testing.assert_array_equal(ignored[1:], 0.0)


@pytest.mark.parametrize("weights, distances, expected", [
    ([[0.0, 1.0, 0.0]], [2.0], 0.0),  # all weight at the known depth (midpoint 2)
    ([[0.0, 0.0, 0.0]], [2.0], 1.0),  # transparent: disparity 0 against 2 / 2
    ([[0.5, 0.0, 0.5]], [2.0], 0.5 * (2 / 1 - 1) ** 2 + 0.5 * (2 / 3 - 1) ** 2),
])
def test_disparity_error_penalises_weight_away_from_the_known_depth(weights, distances,
                                                                    expected):
  edges = np.array([[0.5, 1.5, 2.5, 3.5]], np.float32)
  value = losses.disparity_error(edges, np.array(weights, np.float32),
                                 np.array(distances, np.float32), 2.0, np.ones(1, np.float32))
  np.testing.assert_allclose(value, expected, rtol=1e-5)
