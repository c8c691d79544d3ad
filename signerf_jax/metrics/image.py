"""PSNR and SSIM in JAX, optionally restricted to a mask (e.g. background preservation).

SSIM follows `skimage.metrics.structural_similarity(..., gaussian_weights=True, sigma=1.5,
use_sample_covariance=False, data_range=1, channel_axis=-1)` (Wang et al. 2004): an 11-tap
Gaussian window (radius int(3.5 sigma + 0.5)) with scipy's 'reflect' borders, and the mean taken
over the map without the (window - 1) / 2 border, then over channels.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

_SIGMA = 1.5
_TRUNCATE = 3.5
_K1, _K2 = 0.01, 0.03


def mse(image, reference, mask=None):
  """Mean squared error over pixels (and channels) where `mask` [H, W] is non-zero (weighted)."""
  squared = jnp.mean((jnp.asarray(image) - jnp.asarray(reference))**2, axis=-1)
  if mask is None:
    return jnp.mean(squared)
  mask = jnp.asarray(mask, jnp.float32)
  return jnp.sum(mask * squared) / jnp.maximum(jnp.sum(mask), 1e-12)


def psnr(image, reference, mask=None, data_range: float = 1.0):
  """Peak signal-to-noise ratio in dB of [H, W, C] images (inf-safe: MSE floored at 1e-10)."""
  return 10.0 * jnp.log10(data_range**2 / jnp.maximum(mse(image, reference, mask), 1e-10))


def _gaussian_kernel() -> np.ndarray:
  radius = int(_TRUNCATE * _SIGMA + 0.5)
  x = np.arange(-radius, radius + 1, dtype=np.float64)
  kernel = np.exp(-0.5 * (x / _SIGMA)**2)
  return (kernel / kernel.sum()).astype(np.float32)


def _blur(images):
  """Separable Gaussian filter of [H, W, C] with scipy's 'reflect' (= numpy 'symmetric') edges."""
  kernel = _gaussian_kernel()
  radius = kernel.shape[0] // 2
  padded = jnp.pad(images, ((radius, radius), (radius, radius), (0, 0)), mode="symmetric")
  height, width = images.shape[:2]
  rows = sum(kernel[i] * padded[i:i + height] for i in range(kernel.shape[0]))
  return sum(kernel[i] * rows[:, i:i + width] for i in range(kernel.shape[0]))


def ssim_map(image, reference, data_range: float = 1.0):
  """Per-pixel, per-channel SSIM [H, W, C] of two [H, W, C] images."""
  x, y = jnp.asarray(image, jnp.float32), jnp.asarray(reference, jnp.float32)
  mean_x, mean_y = _blur(x), _blur(y)
  variance_x = _blur(x * x) - mean_x**2
  variance_y = _blur(y * y) - mean_y**2
  covariance = _blur(x * y) - mean_x * mean_y
  c1, c2 = (_K1 * data_range)**2, (_K2 * data_range)**2
  return ((2 * mean_x * mean_y + c1) * (2 * covariance + c2) /
          ((mean_x**2 + mean_y**2 + c1) * (variance_x + variance_y + c2)))


def ssim(image, reference, mask=None, data_range: float = 1.0):
  """Mean SSIM of [H, W, C] images, over the map without its window border (as skimage), or
  weighted by `mask` [H, W] within that region."""
  radius = _gaussian_kernel().shape[0] // 2
  values = ssim_map(image, reference, data_range)[radius:-radius, radius:-radius]
  per_pixel = jnp.mean(values, axis=-1)
  if mask is None:
    return jnp.mean(per_pixel)
  mask = jnp.asarray(mask, jnp.float32)[radius:-radius, radius:-radius]
  return jnp.sum(mask * per_pixel) / jnp.maximum(jnp.sum(mask), 1e-12)


psnr_jit = jax.jit(psnr)
ssim_jit = jax.jit(ssim)
