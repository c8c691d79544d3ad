"""Input encodings: the multiresolution hash grid (instant-NGP) and spherical harmonics.

The hash grid keeps ONE flat feature table for all levels and gathers each cube corner for all
levels at once: on CPU a Python loop over levels (many small gathers) is ~100x slower than these
eight large gathers (see shared/notes/cpu-performance.md). Levels whose (resolution + 1)^3 vertices
fit in their table slot are stored densely (exact, no collisions); only finer levels are hashed.
"""

from __future__ import annotations

import dataclasses
import math

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

# instant-NGP's spatial hash primes (the first is 1 so that x stays coherent in memory).
_HASH_PRIMES = (1, 2654435761, 805459861)
# The eight corners of a unit cube, [8, 3].
_CORNERS = np.array([[(i >> 2) & 1, (i >> 1) & 1, i & 1] for i in range(8)], np.uint32)


@dataclasses.dataclass(frozen=True)
class GridLayout:
  """Where each level of a multiresolution grid lives in the flat table (all static).

  Attributes:
    resolutions: per level, the number of cells along each axis.
    table_sizes: per level, the number of feature rows it owns.
    offsets: per level, its first row in the flat table.
    dense: per level, True when stored densely (row = x + y (N+1) + z (N+1)^2).
    features_per_level: features stored per row.
  """

  resolutions: tuple[int, ...]
  table_sizes: tuple[int, ...]
  offsets: tuple[int, ...]
  dense: tuple[bool, ...]
  features_per_level: int

  @property
  def num_levels(self) -> int:
    return len(self.resolutions)

  @property
  def num_rows(self) -> int:
    return self.offsets[-1] + self.table_sizes[-1]

  @property
  def output_dim(self) -> int:
    return self.num_levels * self.features_per_level


def grid_layout(num_levels: int, base_resolution: int, finest_resolution: int,
                log2_table_size: int, features_per_level: int) -> GridLayout:
  """Lays out a geometric series of grid resolutions from base to finest.

  Args:
    num_levels: number of resolutions L >= 1.
    base_resolution, finest_resolution: cells per axis at the coarsest / finest level.
    log2_table_size: log2 of the maximum rows per hashed level.
    features_per_level: features per row F.
  """
  if num_levels == 1:
    resolutions = (int(finest_resolution),)
  else:
    growth = math.exp((math.log(finest_resolution) - math.log(base_resolution)) / (num_levels - 1))
    resolutions = tuple(int(math.floor(base_resolution * growth**level + 1e-6))
                        for level in range(num_levels))
  max_rows = 2**log2_table_size
  table_sizes, dense, offsets, offset = [], [], [], 0
  for resolution in resolutions:
    vertices = (resolution + 1)**3
    is_dense = vertices <= max_rows
    # Rows are padded to a multiple of 8 so the next level starts aligned; a hashed level keeps
    # its power-of-two size (at least 8), which `_corner_rows` relies on.
    size = int(math.ceil(vertices / 8) * 8) if is_dense else max(max_rows, 8)
    table_sizes.append(size)
    dense.append(is_dense)
    offsets.append(offset)
    offset += size
  return GridLayout(resolutions, tuple(table_sizes), tuple(offsets), tuple(dense),
                    features_per_level)


def _axis_terms(layout: GridLayout, lower: jax.Array) -> jax.Array:
  """Each axis's share of a vertex's row, for the cell's lower and upper vertex along it.

  A dense row is x + (N+1) y + (N+1)^2 z and a hashed one x p0 ^ y p1 ^ z p2: both combine one
  term per axis, so the eight corners of a cell need these six terms and two additions or XORs
  each, not three multiplications (the encoding's index arithmetic took over half as long
  as its gathers).

  Args:
    lower: [..., L, 3] uint32 lower vertex of each level's cell.
  Returns:
    [..., L, 3, 2] uint32: axis terms of the lower (0) and upper (1) vertex.
  """
  vertices = np.asarray(layout.resolutions, np.uint32) + 1
  dense_factors = np.stack([np.ones_like(vertices), vertices, vertices * vertices], -1)
  factors = np.where(np.asarray(layout.dense)[:, None], dense_factors,
                     np.asarray(_HASH_PRIMES, np.uint32)).astype(np.uint32)  # [L, 3]
  return jnp.stack([lower, lower + np.uint32(1)], -1) * factors[:, :, None]


def _corner_rows(layout: GridLayout, terms: jax.Array, corner: np.ndarray) -> jax.Array:
  """Flat-table rows of one corner of each level's cell.

  Args:
    terms: [..., L, 3, 2] from `_axis_terms`.
    corner: [3] 0 or 1 per axis.
  Returns:
    [..., L] int32 rows in the flat table.
  """
  x, y, z = (terms[..., axis, int(corner[axis])] for axis in range(3))
  rows = jnp.where(np.asarray(layout.dense), x + y + z, x ^ y ^ z)
  # Dense rows are in range already; hashed tables have power-of-two sizes, so the modulo is a
  # mask (the integer division per element was a tenth of the encoding's time).
  masks = np.asarray([0xFFFFFFFF if dense else size - 1
                      for dense, size in zip(layout.dense, layout.table_sizes)], np.uint32)
  return ((rows & masks) + np.asarray(layout.offsets, np.uint32)).astype(jnp.int32)


def hash_grid_encode(table: jax.Array, layout: GridLayout, points: jax.Array,
                     level_weights: jax.Array | None = None) -> jax.Array:
  """Trilinearly interpolated features of every level at `points`.

  Args:
    table: [layout.num_rows, F] float features.
    layout: the static grid layout.
    points: [..., 3] positions in [0, 1]^3 (values outside are clamped to the border).
    level_weights: None or [L] factors on each level's features (coarse-to-fine training:
      `level_weights_at`); a zero level gets no gradient either.
  Returns:
    [..., L * F] features, level-major.
  """
  resolutions = np.asarray(layout.resolutions, np.float32)
  scaled = jnp.clip(points, 0.0, 1.0)[..., None, :] * resolutions[:, None]  # [..., L, 3]
  # The top face (scaled == N) uses cell N - 1 with fraction 1, keeping corner N + 1 unused.
  lower = jnp.minimum(jnp.floor(scaled), resolutions[:, None] - 1.0)
  fraction = scaled - lower
  terms = _axis_terms(layout, lower.astype(jnp.uint32))
  axis_weights = jnp.stack([1.0 - fraction, fraction], -1)  # [..., L, 3, 2]
  features = 0.0
  for corner in _CORNERS:
    rows = _corner_rows(layout, terms, corner)
    weight = (axis_weights[..., 0, corner[0]] * axis_weights[..., 1, corner[1]]
              * axis_weights[..., 2, corner[2]])  # [..., L]
    corner_features = table.at[rows].get(mode="promise_in_bounds")  # [..., L, F]
    features = features + weight[..., None] * corner_features
  if level_weights is not None:
    features = features * level_weights[:, None]
  return features.reshape(*points.shape[:-1], layout.output_dim)


def level_weights_at(num_levels: int, progress, anneal_fraction: float) -> jax.Array:
  """[L] coarse-to-fine weights of the grid levels at training `progress` in [0, 1].

  The coarsest level is on from the start; the others fade in one after another (each over an
  equal share) until `anneal_fraction` of training, so the field first fits what all views
  agree on coarsely before fine levels can memorise single views (Neuralangelo, FreeNeRF).
  """
  if num_levels == 1 or anneal_fraction <= 0:
    return jnp.ones(num_levels, jnp.float32)
  unlocked = jnp.clip(progress / anneal_fraction, 0.0, 1.0) * (num_levels - 1)
  return jnp.clip(unlocked - jnp.arange(num_levels, dtype=jnp.float32) + 1.0, 0.0, 1.0)


class HashGridEncoding(nn.Module):
  """Flax wrapper owning the flat feature table of `hash_grid_encode`."""

  layout: GridLayout
  init_scale: float = 1e-4

  @nn.compact
  def __call__(self, points: jax.Array, level_weights: jax.Array | None = None) -> jax.Array:
    """points: [..., 3] in [0, 1]^3 -> [..., L * F] features (`hash_grid_encode`)."""
    table = self.param(
        "table",
        lambda key, shape: jax.random.uniform(key, shape, jnp.float32, -self.init_scale,
                                              self.init_scale),
        (self.layout.num_rows, self.layout.features_per_level))
    return hash_grid_encode(table, self.layout, points, level_weights)


def spherical_harmonics(directions: jax.Array, degree: int = 4) -> jax.Array:
  """Real spherical harmonics of unit directions up to `degree` (exclusive), as instant-NGP.

  Args:
    directions: [..., 3] unit vectors.
    degree: 1 to 4; the output has degree**2 channels.
  Returns:
    [..., degree**2] float32.
  """
  x, y, z = directions[..., 0], directions[..., 1], directions[..., 2]
  xx, yy, zz = x * x, y * y, z * z
  components = [jnp.full_like(x, 0.28209479177387814)]
  if degree > 1:
    components += [-0.48860251190291987 * y, 0.48860251190291987 * z, -0.48860251190291987 * x]
  if degree > 2:
    components += [1.0925484305920792 * x * y, -1.0925484305920792 * y * z,
                   0.94617469575755997 * zz - 0.31539156525251999,
                   -1.0925484305920792 * x * z, 0.54627421529603959 * (xx - yy)]
  if degree > 3:
    components += [0.59004358992664352 * y * (-3.0 * xx + yy), 2.8906114426405538 * x * y * z,
                   0.45704579946446572 * y * (1.0 - 5.0 * zz),
                   0.3731763325901154 * z * (5.0 * zz - 3.0),
                   0.45704579946446572 * x * (1.0 - 5.0 * zz),
                   1.4453057213202769 * z * (xx - yy), 0.59004358992664352 * x * (-xx + 3.0 * yy)]
  return jnp.stack(components, axis=-1)
