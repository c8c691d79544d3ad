"""The inpainting mask as diffusers' pipelines process it, and the final paste-back.

Numerical conventions that match diffusers exactly:
  * binarisation (`VaeImageProcessor(do_binarize=True)`): m < 0.5 -> 0 (keep), else 1
    (regenerate), at pixel resolution; the masked image is image * (m < 0.5);
  * the latent mask: `torch.nn.functional.interpolate(mask, size=latent_size)` (mode "nearest",
    source index floor(i * in / out) in float32), see `downsample_mask`;
  * the paste-back's blur is PIL's `GaussianBlur` (`VaeImageProcessor.blur`) without its rounding
    to 8 bits, and the paste-back is diffusers' `apply_overlay` in float.
Masks are NHWC: [B, H, W, 1] at pixel resolution, [B, h, w, 1] at latent resolution.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

BLUR_PASSES = 3  # PIL's GaussianBlur: three box blurs per axis.


def binarize_mask(mask: jax.Array) -> jax.Array:
  """diffusers' mask binarisation: values < 0.5 -> 0 (keep), the rest -> 1 (regenerate)."""
  return jnp.where(mask < 0.5, 0.0, 1.0).astype(jnp.float32)


def nearest_source_indices(input_size: int, output_size: int) -> np.ndarray:
  """torch's "nearest" interpolation: source index min(floor(i * in / out), in - 1), float32."""
  scale = np.float32(input_size) / np.float32(output_size)
  indices = np.floor(np.arange(output_size, dtype=np.float32) * scale).astype(np.int64)
  return np.minimum(indices, input_size - 1)


def downsample_mask(mask: jax.Array, latent_height: int, latent_width: int) -> jax.Array:
  """[B, H, W, 1] -> [B, h, w, 1] exactly as diffusers' `prepare_mask_latents` resizes it.

  For H = 8h this takes pixel (8i, 8j), the top-left pixel of each latent cell.
  """
  rows = nearest_source_indices(mask.shape[1], latent_height)
  columns = nearest_source_indices(mask.shape[2], latent_width)
  return mask[:, rows][:, :, columns]


def _gaussian_box_radius(radius: float) -> float:
  """PIL's `_gaussian_blur_radius`: the fractional box radius whose BLUR_PASSES-fold repetition
  has the variance of a Gaussian of standard deviation `radius` (Gwosdek et al. 2011)."""
  variance = radius * radius / BLUR_PASSES
  integral = math.floor((math.sqrt(12.0 * variance + 1.0) - 1.0) / 2.0)
  fraction = ((2 * integral + 1) * (integral * (integral + 1) - 3 * variance) /
              (6 * (variance - (integral + 1)**2)))
  return integral + fraction


def _box_kernel(box_radius: float) -> np.ndarray:
  """PIL's extended box: 2l + 1 taps of weight 1 / (2r + 1) and a partial tap at each end."""
  integral = int(box_radius)
  weight = 1.0 / (2.0 * box_radius + 1.0)
  edge = (1.0 - (2 * integral + 1) * weight) / 2.0
  return np.asarray([edge] + [weight] * (2 * integral + 1) + [edge], np.float32)


def blur_mask(mask: jax.Array, radius: float) -> jax.Array:
  """diffusers' `VaeImageProcessor.blur` (PIL `ImageFilter.GaussianBlur(radius)`) in float.

  PIL approximates the Gaussian by three extended box blurs along rows, then three along
  columns, with edge pixels repeated; this is that filter without PIL's rounding to 8 bits after
  every pass (the results differ by at most a few 1/255).

  Args:
    mask: [B, H, W, 1] float32.
    radius: the Gaussian's standard deviation in pixels (`blur_factor`); 0 returns `mask`.
  """
  if radius <= 0:
    return mask
  kernel = _box_kernel(_gaussian_box_radius(radius))
  half = len(kernel) // 2
  for axis, kernel_shape in ((2, (1, len(kernel), 1, 1)), (1, (len(kernel), 1, 1, 1))):
    for _ in range(BLUR_PASSES):
      padding = [(0, 0)] * 4
      padding[axis] = (half, half)
      mask = jax.lax.conv_general_dilated(
          jnp.pad(mask, padding, mode="edge"), jnp.asarray(kernel).reshape(kernel_shape),
          (1, 1), "VALID", dimension_numbers=("NHWC", "HWIO", "NHWC"),
          precision=jax.lax.Precision.HIGHEST)
  return mask


def paste_back(original: jax.Array, generated: jax.Array, mask: jax.Array) -> jax.Array:
  """original * (1 - mask) + generated * mask: diffusers' `apply_overlay` in float.

  Args:
    original, generated: [B, H, W, 3] in [0, 1].
    mask: [B, H, W, 1] in [0, 1] (soft values blend).
  """
  return original * (1.0 - mask) + generated * mask
