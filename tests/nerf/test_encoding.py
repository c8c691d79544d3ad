import jax
import jax.numpy as jnp
import numpy as np
import pytest

from signerf_jax.nerf import encoding


def reference_encode(table, layout, points):
  """Per-level, per-corner loops in numpy: slow but obviously right."""
  table, points = np.asarray(table), np.clip(np.asarray(points, np.float64), 0, 1)
  outputs = []
  for level in range(layout.num_levels):
    resolution = layout.resolutions[level]
    scaled = points * resolution
    lower = np.minimum(np.floor(scaled), resolution - 1).astype(np.int64)
    fraction = scaled - lower
    features = 0
    for corner in np.ndindex(2, 2, 2):
      cell = lower + np.array(corner)
      if layout.dense[level]:
        row = cell[:, 0] + (resolution + 1) * (cell[:, 1] + (resolution + 1) * cell[:, 2])
      else:
        row = (cell[:, 0] ^ (cell[:, 1] * 2654435761) ^ (cell[:, 2] * 805459861)) & 0xFFFFFFFF
      row = row % layout.table_sizes[level] + layout.offsets[level]
      weight = np.prod(np.where(np.array(corner) == 1, fraction, 1 - fraction), axis=-1)
      features = features + weight[:, None] * table[row]
    outputs.append(features)
  return np.concatenate(outputs, axis=-1)


def test_flat_table_encoding_matches_per_level_reference():
  layout = encoding.grid_layout(5, 4, 40, 10, 2)
  assert any(layout.dense) and not all(layout.dense)  # Both kinds of level.
  table = jax.random.normal(jax.random.PRNGKey(0), (layout.num_rows, 2))
  points = jax.random.uniform(jax.random.PRNGKey(1), (300, 3), minval=-0.1, maxval=1.1)
  np.testing.assert_allclose(encoding.hash_grid_encode(table, layout, points),
                             reference_encode(table, layout, points), atol=1e-5)


def test_layout_is_geometric_with_dense_coarse_levels():
  layout = encoding.grid_layout(6, 16, 512, 14, 2)
  assert layout.resolutions[0] == 16 and layout.resolutions[-1] == 512
  ratios = np.diff(np.log(layout.resolutions))
  np.testing.assert_allclose(ratios, ratios[0], atol=0.05)
  for resolution, size, dense in zip(layout.resolutions, layout.table_sizes, layout.dense):
    assert dense == ((resolution + 1)**3 <= 2**14)
    assert size <= max((resolution + 1)**3 + 7, 2**14)
  assert layout.offsets[1:] == tuple(np.cumsum(layout.table_sizes)[:-1])


def test_dense_levels_interpolate_linear_functions_exactly():
  layout = encoding.grid_layout(1, 8, 8, 20, 1)
  assert layout.dense == (True,)
  vertices = np.stack(np.meshgrid(*[np.arange(9)] * 3, indexing="ij"), -1).reshape(-1, 3) / 8
  # Rows are x-fastest: row = x + 9 (y + 9 z).
  order = np.lexsort((vertices[:, 0], vertices[:, 1], vertices[:, 2]))
  values = vertices[order] @ np.array([1.0, -2.0, 0.5])
  table = np.zeros((layout.num_rows, 1), np.float32)
  table[:len(values), 0] = values
  points = np.random.default_rng(0).uniform(0, 1, (100, 3)).astype(np.float32)
  np.testing.assert_allclose(encoding.hash_grid_encode(jnp.asarray(table), layout, points)[:, 0],
                             points @ np.array([1.0, -2.0, 0.5]), atol=1e-5)


def test_gradients_reach_only_touched_rows_and_are_finite():
  layout = encoding.grid_layout(3, 4, 16, 8, 2)
  table = jnp.zeros((layout.num_rows, 2))
  points = jnp.array([[0.5, 0.5, 0.5], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0]])
  gradient = jax.grad(lambda t: jnp.sum(encoding.hash_grid_encode(t, layout, points)))(table)
  assert np.all(np.isfinite(gradient))
  touched = np.count_nonzero(np.abs(np.asarray(gradient)).sum(-1))
  assert 0 < touched <= 3 * 8 * layout.num_levels
  # Each point's trilinear weights sum to one per level and feature.
  np.testing.assert_allclose(np.sum(gradient), 3 * layout.num_levels * 2, rtol=1e-5)


def test_spherical_harmonics_are_orthonormal():
  directions = jax.random.normal(jax.random.PRNGKey(0), (200000, 3))
  directions = directions / jnp.linalg.norm(directions, axis=-1, keepdims=True)
  basis = encoding.spherical_harmonics(directions, 4)
  assert basis.shape == (200000, 16)
  gram = 4 * np.pi * np.asarray(basis.T @ basis) / basis.shape[0]
  np.testing.assert_allclose(gram, np.eye(16), atol=0.03)


def test_coarse_to_fine_weights_unlock_levels_in_order():
  weights = lambda progress: np.asarray(encoding.level_weights_at(5, progress, 0.5))
  np.testing.assert_array_equal(weights(0.0), [1, 0, 0, 0, 0])
  np.testing.assert_allclose(weights(0.25), [1, 1, 1, 0, 0], atol=1e-6)  # halfway: 2 of 4 more
  np.testing.assert_allclose(weights(0.3125), [1, 1, 1, 0.5, 0], atol=1e-6)
  np.testing.assert_array_equal(weights(0.5), np.ones(5))
  np.testing.assert_array_equal(weights(1.0), np.ones(5))
  np.testing.assert_array_equal(encoding.level_weights_at(5, 0.0, 0.0), np.ones(5))


@pytest.mark.slow
def test_a_switched_off_level_has_no_features_and_no_gradient():
  layout = encoding.grid_layout(3, 4, 16, 10, 2)
  table = jax.random.normal(jax.random.PRNGKey(0), (layout.num_rows, 2))
  points = jax.random.uniform(jax.random.PRNGKey(1), (20, 3))
  level_weights = jnp.array([1.0, 0.5, 0.0])
  features = encoding.hash_grid_encode(table, layout, points, level_weights).reshape(20, 3, 2)
  full = encoding.hash_grid_encode(table, layout, points).reshape(20, 3, 2)
  np.testing.assert_allclose(features, full * level_weights[:, None], rtol=1e-6)
  gradient = jax.grad(lambda t: jnp.sum(encoding.hash_grid_encode(t, layout, points,
                                                                  level_weights)))(table)
  finest = slice(layout.offsets[2], layout.offsets[2] + layout.table_sizes[2])
  assert np.all(gradient[finest] == 0) and np.any(gradient[:layout.table_sizes[0]] != 0)
