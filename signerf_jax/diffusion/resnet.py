"""diffusers' ResnetBlock2D and the resamplers between resolutions, in NHWC layout.

The UNet, the ControlNet and the VAE all build their blocks from these: `ResnetBlock2D` (with
the timestep embedding in the UNet and ControlNet, without it in the VAE), `Downsample2D` (a
stride-2 convolution) and `Upsample2D` (nearest x2 then a convolution, computed at the input
resolution by `layers.UpsampleConv`). Parameter names are diffusers'.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from signerf_jax.diffusion.layers import Conv2d, Dtype, GroupNorm, Linear, UpsampleConv


class ResnetBlock2D(nn.Module):
  """diffusers' ResnetBlock2D ("default" time-embedding norm, pre-norm, SiLU).

  x [B, H, W, C_in], time_embedding [B, T] or None -> [B, H, W, out_channels].
  """
  out_channels: int
  groups: int
  epsilon: float
  output_scale_factor: float = 1.0
  compute_dtype: Dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array, time_embedding: jax.Array | None = None) -> jax.Array:
    conv = lambda name, **kw: Conv2d(self.out_channels, name=name, compute_dtype=self.compute_dtype,
                                     **kw)
    h = nn.silu(GroupNorm(self.groups, self.epsilon, name="norm1")(x))
    h = conv("conv1")(h)
    if time_embedding is not None:
      shift = Linear(self.out_channels, name="time_emb_proj", compute_dtype=self.compute_dtype)(
          nn.silu(time_embedding))
      h = h + shift[:, None, None, :]
    h = nn.silu(GroupNorm(self.groups, self.epsilon, name="norm2")(h))
    h = conv("conv2")(h)
    if x.shape[-1] != self.out_channels:
      x = conv("conv_shortcut", kernel_size=1, padding=0)(x)
    residual = x + h
    return residual if self.output_scale_factor == 1 else residual / self.output_scale_factor


class Downsample2D(nn.Module):
  """Stride-2 3x3 convolution. padding 0 means diffusers' asymmetric (0, 1) pad (the VAE's)."""
  channels: int
  padding: int = 1
  compute_dtype: Dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    padding = ((0, 1), (0, 1)) if self.padding == 0 else self.padding
    return Conv2d(self.channels, stride=2, padding=padding, name="conv",
                  compute_dtype=self.compute_dtype)(x)


class Upsample2D(nn.Module):
  """diffusers' Upsample2D with a convolution: nearest x2 (or to `size`), 3x3 conv."""
  channels: int
  compute_dtype: Dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array, size: tuple[int, int] | None = None) -> jax.Array:
    return UpsampleConv(self.channels, self.compute_dtype, name="conv")(x, size)
