"""diffusers' AutoencoderKL in Flax: images <-> latent diagonal Gaussians.

Layout: images are NHWC [B, H, W, 3] in [-1, 1] (diffusers' convention; map [0, 1] images with
2x - 1); latents are NHWC [B, H/8, W/8, latent_channels] for the usual four blocks. `encode`
returns the posterior (`DiagonalGaussian`); the diffusion model works on
`config.to_diffusion_latents(z)` = (z - shift_factor) * scaling_factor, and `decode` takes z
back (`config.from_diffusion_latents`).

    module, params = load_vae("checkpoint/vae")
    posterior = module.apply({"params": params}, images, method=module.encode)
    latents = module.config.to_diffusion_latents(posterior.sample(key))
    images = module.apply({"params": params},
                          module.config.from_diffusion_latents(latents), method=module.decode)
"""

from __future__ import annotations

import os

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from signerf_jax.diffusion import model_configs, weights
from signerf_jax.diffusion.attention import AttentionOptions, multi_head_attention
from signerf_jax.diffusion.layers import (Conv2d, Downsample2D, Dtype, GroupNorm, ResnetBlock2D,
                                          Upsample2D)

EPSILON = 1e-6  # diffusers' Encoder/Decoder use eps 1e-6 in every norm.
# Tensor names of checkpoints saved before diffusers renamed the VAE's attention layers.
_LEGACY_ATTENTION_NAMES = {"query": "to_q", "key": "to_k", "value": "to_v",
                           "proj_attn": "to_out.0"}


@struct.dataclass
class DiagonalGaussian:
  """The encoder's posterior N(mean, exp(logvar)) per latent element, both [B, h, w, C]."""
  mean: jax.Array
  logvar: jax.Array

  @classmethod
  def from_moments(cls, moments: jax.Array) -> "DiagonalGaussian":
    """Splits [..., 2C] moments into mean and log-variance (clamped to [-30, 20] as diffusers)."""
    mean, logvar = jnp.split(moments, 2, axis=-1)
    return cls(mean, jnp.clip(logvar, -30.0, 20.0))

  @property
  def std(self) -> jax.Array:
    return jnp.exp(0.5 * self.logvar)

  def mode(self) -> jax.Array:
    return self.mean

  def sample_from_noise(self, noise: jax.Array) -> jax.Array:
    """mean + std * noise, for a standard-normal `noise` shaped like the mean."""
    return self.mean + self.std * noise

  def sample(self, key: jax.Array) -> jax.Array:
    return self.sample_from_noise(jax.random.normal(key, self.mean.shape, self.mean.dtype))


class MidBlock(nn.Module):
  """UNetMidBlock2D without time embedding: resnet, single-head self-attention, resnet."""
  groups: int
  add_attention: bool
  attention: AttentionOptions = AttentionOptions()
  compute_dtype: Dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    channels = x.shape[-1]
    resnet = lambda name: ResnetBlock2D(channels, self.groups, EPSILON, 1.0, self.compute_dtype,
                                        name=name)
    x = resnet("resnets_0")(x)
    if self.add_attention:
      x = x + _SpatialAttention(self.groups, self.attention, self.compute_dtype,
                                name="attentions_0")(x)
    return resnet("resnets_1")(x)


class _SpatialAttention(nn.Module):
  """GroupNorm then one head over all H*W positions (no residual; the caller adds it)."""
  groups: int
  attention: AttentionOptions
  compute_dtype: Dtype

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    batch, channels = x.shape[0], x.shape[-1]
    tokens = GroupNorm(self.groups, EPSILON, name="group_norm")(x).reshape(batch, -1, channels)
    out = multi_head_attention(tokens, tokens, 1, channels, channels, True, self.attention,
                               self.compute_dtype)
    return out.reshape(x.shape)


class ResnetStack(nn.Module):
  """DownEncoderBlock2D (resample "down": asymmetric-pad stride-2 conv) or UpDecoderBlock2D
  (resample "up": nearest x2 and a conv): resnets without time embedding, then the resampling."""
  out_channels: int
  num_layers: int
  groups: int
  resample: str | None
  compute_dtype: Dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    for layer in range(self.num_layers):
      x = ResnetBlock2D(self.out_channels, self.groups, EPSILON, 1.0, self.compute_dtype,
                        name=f"resnets_{layer}")(x)
    if self.resample == "down":
      x = Downsample2D(self.out_channels, 0, self.compute_dtype, name="downsamplers_0")(x)
    elif self.resample == "up":
      x = Upsample2D(self.out_channels, self.compute_dtype, name="upsamplers_0")(x)
    return x


class Encoder(nn.Module):
  """Images [B, H, W, in_channels] -> moments [B, h, w, 2 * latent_channels]."""
  config: model_configs.AutoencoderConfig
  attention: AttentionOptions = AttentionOptions()
  compute_dtype: Dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    config, dtype = self.config, self.compute_dtype
    channels, groups = config.block_out_channels, config.norm_num_groups
    x = Conv2d(channels[0], compute_dtype=dtype, name="conv_in")(x)
    for index, block_channels in enumerate(channels):
      x = ResnetStack(block_channels, config.layers_per_block, groups,
                      "down" if index < len(channels) - 1 else None, dtype,
                      name=f"down_blocks_{index}")(x)
    x = MidBlock(groups, config.mid_block_add_attention, self.attention, dtype,
                 name="mid_block")(x)
    x = nn.silu(GroupNorm(groups, EPSILON, name="conv_norm_out")(x))
    return Conv2d(2 * config.latent_channels, compute_dtype=dtype, name="conv_out")(x)


class Decoder(nn.Module):
  """Latents [B, h, w, latent_channels] -> images [B, H, W, out_channels]."""
  config: model_configs.AutoencoderConfig
  attention: AttentionOptions = AttentionOptions()
  compute_dtype: Dtype = jnp.float32

  @nn.compact
  def __call__(self, z: jax.Array) -> jax.Array:
    config, dtype = self.config, self.compute_dtype
    channels, groups = config.block_out_channels[::-1], config.norm_num_groups
    x = Conv2d(channels[0], compute_dtype=dtype, name="conv_in")(z)
    x = MidBlock(groups, config.mid_block_add_attention, self.attention, dtype,
                 name="mid_block")(x)
    for index, block_channels in enumerate(channels):
      x = ResnetStack(block_channels, config.layers_per_block + 1, groups,
                      "up" if index < len(channels) - 1 else None, dtype,
                      name=f"up_blocks_{index}")(x)
    x = nn.silu(GroupNorm(groups, EPSILON, name="conv_norm_out")(x))
    return Conv2d(config.out_channels, compute_dtype=dtype, name="conv_out")(x)


class AutoencoderKL(nn.Module):
  """The VAE; `encode` and `decode` are its entry points (`__call__` runs both, for init)."""
  config: model_configs.AutoencoderConfig
  attention: AttentionOptions = AttentionOptions()
  compute_dtype: Dtype = jnp.float32

  def setup(self):
    config, dtype = self.config, self.compute_dtype
    self.encoder = Encoder(config, self.attention, dtype)
    self.decoder = Decoder(config, self.attention, dtype)
    if config.use_quant_conv:
      self.quant_conv = Conv2d(2 * config.latent_channels, 1, padding=0, compute_dtype=dtype)
    if config.use_post_quant_conv:
      self.post_quant_conv = Conv2d(config.latent_channels, 1, padding=0, compute_dtype=dtype)

  def encode(self, images: jax.Array) -> DiagonalGaussian:
    """images [B, H, W, in_channels] in [-1, 1] -> posterior over [B, H/f, W/f, latent] latents."""
    moments = self.encoder(images)
    if self.config.use_quant_conv:
      moments = self.quant_conv(moments)
    return DiagonalGaussian.from_moments(moments)

  def decode(self, latents: jax.Array) -> jax.Array:
    """Unscaled latents z [B, h, w, latent_channels] -> images [B, H, W, out_channels] ~[-1, 1]."""
    if self.config.use_post_quant_conv:
      latents = self.post_quant_conv(latents)
    return self.decoder(latents)

  def __call__(self, images: jax.Array) -> jax.Array:
    return self.decode(self.encode(images).mode())

  def example_inputs(self) -> dict[str, jax.ShapeDtypeStruct]:
    """Abstract inputs of the smallest valid size, for shape inference (`weights`)."""
    size = 2 ** (len(self.config.block_out_channels) - 1)
    return dict(images=jax.ShapeDtypeStruct((1, size, size, self.config.in_channels),
                                            jnp.float32))


def _rename_legacy_attention(tensors: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
  """Maps pre-0.14 diffusers VAE attention names (query, key, value, proj_attn) to current ones."""
  renamed = {}
  for name, tensor in tensors.items():
    prefix, _, rest = name.partition(".attentions.0.")
    layer, _, leaf = rest.partition(".")
    if rest and layer in _LEGACY_ATTENTION_NAMES:
      name = f"{prefix}.attentions.0.{_LEGACY_ATTENTION_NAMES[layer]}.{leaf}"
    renamed[name] = tensor
  return renamed


def load_vae(path: str | os.PathLike, dtype=np.float32, *, variant: str | None = None,
             attention: AttentionOptions | None = None, compute_dtype: Dtype = jnp.float32
             ) -> tuple[AutoencoderKL, dict]:
  """Builds the AutoencoderKL of a diffusers `vae/` directory and loads its safetensors.

  Arguments as `unet.load_unet`; `path` may be a pipeline directory containing `vae/`.
  """
  directory = model_configs.component_directory(path, "vae")
  config = model_configs.AutoencoderConfig.from_dict(model_configs.read_config(directory),
                                                     directory / "config.json")
  module = AutoencoderKL(config, attention or AttentionOptions(), compute_dtype)
  return module, weights.load_params(module, directory, dtype, variant,
                                     rename=_rename_legacy_attention)
