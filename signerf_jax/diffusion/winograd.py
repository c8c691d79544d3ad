"""3x3 convolutions by Winograd's minimal filtering F(m x m, 3 x 3) (Lavin and Gray, 2016).

An m x m output tile comes from an (m + 2) x (m + 2) input tile: both are moved into the
Winograd domain by small constant matrices (B^T d B for the input tile, G g G^T for the kernel),
multiplied there position by position -- (m + 2)^2 independent [tiles, C] x [C, O] matmuls --
and moved back by A^T (.) A. Against the 9 m^2 multiply-adds per output channel and input
channel of a direct convolution that is 36 / 16 = 2.25x fewer FLOPs for m = 2 and 144 / 36 = 4x
fewer for m = 4. The transforms are adds and a few constant multiplies, written out term by
term (a matmul with a tiny constant matrix compiles to slow transposes) and applied separably:
along the rows of all tiles at once, then along their columns, which gives XLA one expression
per row and per column of a tile to compile instead of one per tile position (SD's UNet compiles
faster). F(4 x 4) also keeps a smaller transformed input (36 / 16 of the input against
16 / 4).

Accuracy: F(2 x 2)'s transforms are exact but for the kernel's halves, so float32 results
agree with direct convolution to ~1e-6 relative; F(4 x 4)'s larger constants (up to 8, and
1/6, 1/24) make it ~2e-5 (measured against XLA's convolution on SD-sized layers).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

# Per output tile size m: B^T [m+2, m+2] (input), G [m+2, 3] (kernel), A^T [m, m+2] (output),
# from the interpolation points 0, 1, -1 (m = 2) and 0, 1, -1, 2, -2 (m = 4), plus infinity.
TRANSFORMS = {
    2: (np.array([[1, 0, -1, 0], [0, 1, 1, 0], [0, -1, 1, 0], [0, 1, 0, -1]]),
        np.array([[1, 0, 0], [0.5, 0.5, 0.5], [0.5, -0.5, 0.5], [0, 0, 1]]),
        np.array([[1, 1, 1, 0], [0, 1, -1, -1]])),
    4: (np.array([[4, 0, -5, 0, 1, 0], [0, -4, -4, 1, 1, 0], [0, 4, -4, -1, 1, 0],
                  [0, -2, -1, 2, 1, 0], [0, 2, -1, -2, 1, 0], [0, 4, 0, -5, 0, 1]]),
        np.array([[1 / 4, 0, 0], [-1 / 6, -1 / 6, -1 / 6], [-1 / 6, 1 / 6, -1 / 6],
                  [1 / 24, 1 / 12, 1 / 6], [1 / 24, -1 / 12, 1 / 6], [0, 0, 1]]),
        np.array([[1, 1, 1, 1, 1, 0], [0, 1, -1, 2, -2, 0], [0, 1, 1, 4, 4, 0],
                  [0, 1, -1, 8, -8, 1]])),
}


def _combine(matrix: np.ndarray, values: list[jax.Array]) -> list[jax.Array]:
  """matrix [rows, len(values)] applied to a list of equally shaped arrays, term by term:
  zero coefficients are skipped and +-1 ones are adds and subtracts."""
  rows = []
  for coefficients in matrix:
    total = None
    for coefficient, value in zip(coefficients, values):
      if coefficient == 0:
        continue
      if total is None:
        total = value if coefficient == 1 else value * float(coefficient)
      elif abs(coefficient) == 1:
        total = total + value if coefficient == 1 else total - value
      else:
        total = total + value * float(coefficient)
    rows.append(total)
  return rows


def conv3x3(x: jax.Array, kernel: jax.Array, compute_dtype: Any, output_tile: int) -> jax.Array:
  """3x3 convolution, stride 1, padding 1, by F(output_tile x output_tile, 3 x 3).

  Args:
    x: [B, H, W, C] with H and W multiples of `output_tile`.
    kernel: [3, 3, C, O] (HWIO).
    compute_dtype: input dtype of the Winograd-domain matmuls (the transforms are float32; the
      matmuls accumulate in float32).
    output_tile: m, 2 or 4 (a key of TRANSFORMS).

  Returns:
    [B, H, W, O] float32.
  """
  input_transform, kernel_transform, output_transform = TRANSFORMS[output_tile]
  size = output_tile + 2
  batch, height, width, channels = x.shape
  out = kernel.shape[-1]
  if height % output_tile or width % output_tile:
    raise ValueError(f"F({output_tile}x{output_tile}, 3x3) needs a height and width divisible "
                     f"by {output_tile}; got {height}x{width}")
  tile_rows, tile_cols = height // output_tile, width // output_tile
  padded = jnp.pad(x.astype(jnp.float32), ((0, 0), (1, 1), (1, 1), (0, 0)))
  # Separably: B^T along the rows of every tile at once, then along the columns.
  rows = jnp.stack(_combine(input_transform,
                            [padded[:, r:r + height:output_tile] for r in range(size)]))
  tiles = jnp.stack(_combine(input_transform, [rows[:, :, :, c:c + width:output_tile]
                                               for c in range(size)]), axis=1)
  tiles = tiles.reshape(size * size, -1, channels).astype(compute_dtype)
  kernels = jnp.stack(_combine(kernel_transform, list(kernel.astype(jnp.float32))))
  kernels = jnp.stack(_combine(kernel_transform, list(kernels.transpose(1, 0, 2, 3))), axis=1)
  kernels = kernels.reshape(size * size, channels, out).astype(compute_dtype)
  products = lax.dot_general(tiles, kernels, (((2,), (1,)), ((0,), (0,))),
                             preferred_element_type=jnp.float32)
  products = products.reshape(size, size, batch, tile_rows, tile_cols, out)
  output = jnp.stack(_combine(output_transform, list(products)))  # [m, size, B, h, w, O]
  output = jnp.stack(_combine(output_transform, list(output.transpose(1, 0, 2, 3, 4, 5))),
                     axis=-2)  # [m (row), B, h, w, m (column), O]
  return output.transpose(1, 2, 0, 3, 4, 5).reshape(batch, height, width, out)
