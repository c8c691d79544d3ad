import jax
import jax.numpy as jnp
import numpy as np

from signerf_jax.nerf import occupancy


def test_compact_keeps_order_pads_and_flags_overflowing_rays():
  mask = jnp.array([[1, 0, 1, 0], [0, 0, 0, 0], [1, 1, 1, 0], [0, 1, 0, 0]], bool)
  indices, valid, complete = occupancy.compact(mask, 4)
  np.testing.assert_array_equal(indices, [0, 2, 8, 9])
  np.testing.assert_array_equal(valid, [True] * 4)
  # Ray 2 needs three samples but only two fit; ray 3 does not fit at all.
  np.testing.assert_array_equal(complete, [True, True, False, False])
  indices, valid, complete = occupancy.compact(mask, 8)
  np.testing.assert_array_equal(indices, [0, 2, 8, 9, 10, 13, 16, 16])
  np.testing.assert_array_equal(valid, [True] * 6 + [False] * 2)
  assert np.all(complete)


def test_unvisited_cells_are_occupied_until_evaluated():
  grid = occupancy.initial_grid(4)
  assert np.all(occupancy.occupied_cells(grid, 0.1, 0.01))

  def density(points):  # dense only in the cube's lower-x half
    return jnp.where(points[:, 0] < 0.5, 10.0, 0.0)

  grid = occupancy.update(grid, density, jax.random.PRNGKey(0), jnp.int32(0), 32, 0.95)
  assert np.sum(grid >= 0) == 32  # only the first 32 cells were visited
  grid = occupancy.update(grid, density, jax.random.PRNGKey(1), jnp.int32(1), 32, 0.95)
  occupied = np.asarray(occupancy.occupied_cells(grid, 0.1, 0.01))
  np.testing.assert_array_equal(occupied[:2], True)
  np.testing.assert_array_equal(occupied[2:], False)
  points = jnp.array([[0.1, 0.5, 0.5], [0.9, 0.5, 0.5], [-5.0, 0.0, 0.0]])
  np.testing.assert_array_equal(occupancy.lookup(jnp.asarray(occupied), points),
                                [True, False, True])


def test_update_decays_to_empty_when_density_vanishes():
  grid = jnp.full((2, 2, 2), 100.0)
  for index in range(20):
    grid = occupancy.update(grid, lambda p: jnp.zeros(p.shape[0]), jax.random.PRNGKey(index),
                            jnp.int32(index), 8, 0.5)
  assert float(grid.max()) < 1e-3
  assert not np.any(occupancy.occupied_cells(grid, 0.1, 0.01) & (grid > 0.11))


def test_rendering_evaluates_every_occupied_sample_whatever_the_piece_size():
  """Pieces smaller than, equal to and larger than the occupied count give the same field,
  zero at empty samples, and the count of occupied samples."""
  mask = jnp.asarray(np.random.default_rng(0).uniform(size=(6, 9)) < 0.4)
  unit_points = jnp.linspace(0.0, 1.0, 6 * 9 * 3).reshape(6, 9, 3)

  def field_at(mask, unit_points, directions, appearance, indices):
    safe = jnp.minimum(indices, mask.size - 1)
    density = unit_points.reshape(-1, 3)[safe, 0] + 1.0
    return jnp.where(indices < mask.size, density, 0.0), jnp.repeat(density[:, None], 3, 1)

  expected = np.where(np.asarray(mask).reshape(-1), np.asarray(unit_points).reshape(-1, 3)[:, 0]
                      + 1.0, 0.0)
  for piece_size in (1, 4, int(mask.sum()), 64):
    density, rgb, count = occupancy.evaluate_every_occupied(
        field_at, mask, unit_points, jnp.zeros((6, 3)), jnp.zeros(6, jnp.int32), piece_size)
    np.testing.assert_allclose(density, expected, err_msg=f"pieces of {piece_size}")
    np.testing.assert_allclose(rgb[:, 0], expected, err_msg=f"pieces of {piece_size}")
    assert int(count) == int(mask.sum())


def test_occupied_box_is_the_smallest_box_around_occupied_cells_with_a_margin():
  occupied = np.zeros((8, 8, 8), bool)
  occupied[5, 1, 3] = occupied[6, 2, 3] = True
  np.testing.assert_allclose(occupancy.occupied_box(occupied, margin_cells=0),
                             [[5 / 8, 1 / 8, 3 / 8], [7 / 8, 3 / 8, 4 / 8]])
  # The margin is clipped to the unit cube.
  occupied[7, 0, 3] = True
  np.testing.assert_allclose(occupancy.occupied_box(occupied, margin_cells=1),
                             [[4 / 8, 0, 2 / 8], [1, 4 / 8, 5 / 8]])
  low, high = occupancy.occupied_box(np.zeros((8, 8, 8), bool))
  assert np.all(low > high)


def test_specks_are_small_faint_groups_of_cells():
  cell_size = 0.1
  faint, dense = 1.0, 100.0  # Alpha across a cell: 0.1 and 1.0.
  grid = np.zeros((16, 16, 16), np.float32)
  grid[2:8, 2:8, 2:8] = faint  # A large faint group: kept.
  grid[12, 12, 12] = faint  # A speck.
  grid[12, 2, 14:16] = faint, dense  # Small but dense somewhere: kept.
  grid[14, 14, 2] = grid[15, 15, 3] = faint  # Diagonal neighbours: one speck of two cells.
  occupied = grid > 0.5
  kept = occupancy.without_specks(grid, occupied, cell_size)
  expected = occupied.copy()
  expected[12, 12, 12] = expected[14, 14, 2] = expected[15, 15, 3] = False
  np.testing.assert_array_equal(kept, expected)
  nothing = np.zeros_like(occupied)
  np.testing.assert_array_equal(occupancy.without_specks(grid, nothing, cell_size), nothing)
