"""Packed compositing (`nerf.packed`) against the dense march layout (`nerf.volume`): the same
outputs, weights, distortion and gradients, for any density, with padding and empty rays."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from signerf_jax import camera
from signerf_jax.nerf import losses, packed, ray_samples, sampling, volume
from signerf_jax.nerf import model as nerf_model
from tests.nerf.small_nerf import small_model

BACKGROUND = jnp.array([0.2, 0.4, 0.6])


def dense_scene(density_scale: float, num_rays: int = 6, num_steps: int = 7, seed: int = 0):
  """Densities [R, N] (0 off a random mask, the last ray empty), rgbs [R, N, 3] and edges
  [R, N + 1] whose last interval is infinite on even rays (the 'last_sample' background)."""
  rng = np.random.default_rng(seed)
  mask = rng.uniform(size=(num_rays, num_steps)) < 0.5
  mask[-1] = False
  densities = np.where(mask, density_scale * rng.uniform(0.5, 1.5, mask.shape), 0.0)
  edges = np.cumsum(rng.uniform(0.0, 0.4, (num_rays, num_steps + 1)), axis=1) + 1.0
  edges[::2, -1] = sampling.MAX_DISTANCE
  rgbs = rng.uniform(size=mask.shape + (3,))
  return mask, *(jnp.asarray(array, jnp.float32) for array in (densities, rgbs, edges))


def pack(mask, densities, rgbs, edges, groups: int) -> packed.PackedSamples:
  """The samples at `mask` [R, N] in `groups` groups, two padding samples more than the fullest
  group holds after each group's samples."""
  num_rays, num_steps = mask.shape
  rays_per_group = num_rays // groups
  per_group = [np.nonzero(part.reshape(-1))[0] for part in np.split(mask, groups)]
  size = max(len(indices) for indices in per_group) + 2
  indices = np.stack([np.pad(found, (0, size - len(found)), constant_values=mask.size // groups)
                      for found in per_group])
  ray, step = indices // num_steps, indices % num_steps
  global_ray = np.minimum(ray, rays_per_group - 1) + rays_per_group * np.arange(groups)[:, None]
  padding = ray >= rays_per_group
  at = lambda array, offset: jnp.where(padding, 0.0, array[global_ray, step + offset])
  return packed.PackedSamples(
      jnp.asarray(ray, jnp.int32), jnp.asarray(step, jnp.int32), at(edges, 0), at(edges, 1),
      at(densities, 0), jnp.where(padding[..., None], 0.7, rgbs[global_ray, step]))


def render_both(mask, densities, rgbs, edges, groups):
  """Outputs, weights [R, N] and distortion of the dense and the packed layout."""
  cos = jnp.full(mask.shape[:1], 0.9)
  dense = volume.volume_render(densities, rgbs, edges, cos, BACKGROUND)
  dense_aux = {"edges": dense["edges"], "weights": dense["weights"]}
  samples = pack(mask, densities, rgbs, dense["edges"], groups)
  outputs, weights = packed.volume_render(samples, dense["edges"][:, 0], dense["edges"][:, -1],
                                          cos, BACKGROUND)
  packed_aux = {"edges": dense["edges"], "packed": (samples, weights)}
  spread = packed.spread(weights, samples, *mask.shape)
  ray_weights = jnp.linspace(0.5, 1.0, mask.shape[0])
  return ((dense, dense["weights"], losses.distortion_loss(dense_aux, 2.0, ray_weights)),
          (outputs, spread, losses.distortion_loss(packed_aux, 2.0, ray_weights)))


@pytest.mark.parametrize("density_scale", [0.0, 1e-5, 1.0, 1e5, 1e10])
@pytest.mark.parametrize("groups", [1, 2])
def test_packed_compositing_matches_the_dense_layout(density_scale, groups):
  mask, densities, rgbs, edges = dense_scene(density_scale)
  (dense, dense_weights, dense_distortion), (outputs, weights, distortion) = render_both(
      mask, densities, rgbs, edges, groups)
  for name in ("rgb", "accumulation", "distance", "depth"):
    np.testing.assert_allclose(outputs[name], dense[name], rtol=1e-5, atol=1e-6, err_msg=name)
  np.testing.assert_allclose(weights, dense_weights, rtol=1e-5, atol=1e-7)
  assert float(distortion) == pytest.approx(float(dense_distortion), rel=1e-4, abs=1e-7)


@pytest.mark.parametrize("density_scale", [0.0, 1.0, 1e10])
def test_packed_gradients_match_the_dense_layout_and_are_finite(density_scale):
  mask, densities, rgbs, edges = dense_scene(density_scale, seed=1)

  def scalar(layout, densities, rgbs):
    outputs, _, distortion = render_both(mask, densities, rgbs, edges, groups=2)[layout]
    return (sum(jnp.sum(outputs[name]) for name in ("rgb", "accumulation", "depth"))
            + distortion)

  # The packed samples' gradients reach the dense inputs through `pack`'s gathers: 0 off mask.
  dense = jax.grad(lambda *inputs: scalar(0, *inputs), argnums=(0, 1))(densities, rgbs)
  packed_gradients = jax.grad(lambda *inputs: scalar(1, *inputs), argnums=(0, 1))(densities,
                                                                                 rgbs)
  for dense_gradient, packed_gradient in zip(dense, packed_gradients):
    assert np.all(np.isfinite(packed_gradient))
    on_mask = mask if dense_gradient.ndim == 2 else mask[..., None]
    np.testing.assert_allclose(packed_gradient, jnp.where(on_mask, dense_gradient, 0.0),
                               rtol=1e-4, atol=1e-6)


def test_an_opaque_sample_keeps_the_transmittance_before_it_and_rays_do_not_mix():
  """Ray 0: optical depths 0.3 then 1e6 (opaque): its second weight is exp(-0.3) exactly, which
  `inclusive - value` would round off at 1e6; ray 1 renders as if alone."""
  samples = packed.PackedSamples(
      ray=jnp.array([[0, 0, 1, 1]]), step=jnp.array([[0, 1, 0, 1]]),
      starts=jnp.array([[1.0, 2.0, 1.0, 2.0]]), ends=jnp.array([[2.0, 3.0, 2.0, 3.0]]),
      densities=jnp.array([[0.3, 1e6, 0.5, 0.25]]), rgbs=jnp.full((1, 4, 3), 0.5))
  weights = packed.compute_weights(samples)
  assert float(weights[0, 1]) == pytest.approx(np.exp(-0.3), rel=1e-6)
  alone, _ = volume.compute_weights(jnp.array([0.5, 0.25]), jnp.array([1.0, 2.0, 3.0]))
  np.testing.assert_allclose(weights[0, 2:], alone, rtol=1e-6)


@pytest.mark.slow
def test_training_renders_packed_as_the_dense_march_would(sphere):
  """The occupancy sampler's training render (packed) against the march's dense samples
  (`ray_samples.field_samples`) composited by `volume`: colours, depths, distortion loss and
  the parameters' gradients."""
  model = small_model(sphere)
  variables = nerf_model.init_variables(model, jax.random.PRNGKey(0))
  rays = camera.random_rays(jax.random.PRNGKey(1), sphere.cameras, 1024)[0]
  key = jax.random.PRNGKey(2)

  def dense(params):
    samples, complete, aux = ray_samples.field_samples(
        model, {**variables, "params": params}, rays, key, True,
        ray_samples.ray_range(model, rays), finish=True)
    outputs = volume.volume_render(*samples, rays.cos_to_optical_axis, model.background)
    return outputs, complete, {**aux, "edges": samples[2], "weights": outputs["weights"]}

  def packed_render(params):
    outputs, aux = nerf_model.render_rays(model, {**variables, "params": params}, rays, key,
                                          training=True)
    assert "packed" in aux
    return outputs, outputs["ray_complete"], aux

  def loss(render):
    def scalar(params):
      outputs, complete, aux = render(params)
      ray_weights = complete.astype(jnp.float32)
      return (jnp.sum(ray_weights[:, None] * outputs["rgb"]**2) + jnp.sum(outputs["depth"])
              + losses.distortion_loss(aux, model.scene.extent, ray_weights))
    return scalar

  (dense_loss, dense_gradients), (packed_loss, packed_gradients) = (
      jax.jit(jax.value_and_grad(loss(render)))(variables["params"])
      for render in (dense, packed_render))
  assert 0.1 < float(jnp.mean(packed_render(variables["params"])[1])) < 1.0  # Some dropped.
  assert float(packed_loss) == pytest.approx(float(dense_loss), rel=1e-5)
  for (path, dense_leaf), packed_leaf in zip(jax.tree_util.tree_leaves_with_path(
      dense_gradients), jax.tree.leaves(packed_gradients)):
    np.testing.assert_allclose(packed_leaf, dense_leaf, rtol=1e-3,
                               atol=1e-5 * float(jnp.max(jnp.abs(dense_leaf))) + 1e-9,
                               err_msg=jax.tree_util.keystr(path))
