"""diffusers' AutoencoderKL in Flax: images <-> latent diagonal Gaussians.

Layout: images are NHWC [B, H, W, 3] in [-1, 1] (diffusers' convention; map [0, 1] images with
2x - 1); latents are NHWC [B, H/8, W/8, latent_channels] for the usual four blocks. `encode`
returns the posterior (`DiagonalGaussian`); the diffusion model works on
`config.to_diffusion_latents(z)` = (z - shift_factor) * scaling_factor, and `decode` takes z
back (`config.from_diffusion_latents`); `encode_to_latents` and `decode_from_latents` do both
ways for a batch, one image at a time.

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
from signerf_jax.diffusion.layers import Conv2d, Dtype, GroupNorm
from signerf_jax.diffusion.resnet import Downsample2D, ResnetBlock2D, Upsample2D

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


class _Half(nn.Module):
  """What the encoder and the decoder are built of: conv_in, resnet stacks from resolution to
  resolution, the mid block and the output head (GroupNorm, SiLU, conv_out).

  Its methods create submodules under diffusers' names, so a subclass calls them from its
  compact `__call__`.
  """
  config: model_configs.AutoencoderConfig
  attention: AttentionOptions = AttentionOptions()
  compute_dtype: Dtype = jnp.float32

  def input_convolution(self, x: jax.Array, features: int) -> jax.Array:
    return Conv2d(features, compute_dtype=self.compute_dtype, name="conv_in")(x)

  def resolutions(self, x: jax.Array, channels: tuple[int, ...], num_layers: int, resample: str,
                  prefix: str) -> jax.Array:
    """One `ResnetStack` per entry of `channels`, resampling (`resample`) after all but the
    last; named `<prefix>_<index>`."""
    for index, block_channels in enumerate(channels):
      x = ResnetStack(block_channels, num_layers, self.config.norm_num_groups,
                      resample if index < len(channels) - 1 else None, self.compute_dtype,
                      name=f"{prefix}_{index}")(x)
    return x

  def middle(self, x: jax.Array) -> jax.Array:
    return MidBlock(self.config.norm_num_groups, self.config.mid_block_add_attention,
                    self.attention, self.compute_dtype, name="mid_block")(x)

  def output(self, x: jax.Array, features: int) -> jax.Array:
    x = nn.silu(GroupNorm(self.config.norm_num_groups, EPSILON, name="conv_norm_out")(x))
    return Conv2d(features, compute_dtype=self.compute_dtype, name="conv_out")(x)


class Encoder(_Half):
  """Images [B, H, W, in_channels] -> moments [B, h, w, 2 * latent_channels]."""

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    channels = self.config.block_out_channels
    x = self.input_convolution(x, channels[0])
    x = self.resolutions(x, channels, self.config.layers_per_block, "down", "down_blocks")
    return self.output(self.middle(x), 2 * self.config.latent_channels)


class Decoder(_Half):
  """Latents [B, h, w, latent_channels] -> images [B, H, W, out_channels]."""

  @nn.compact
  def __call__(self, z: jax.Array) -> jax.Array:
    channels = self.config.block_out_channels[::-1]
    x = self.middle(self.input_convolution(z, channels[0]))
    x = self.resolutions(x, channels, self.config.layers_per_block + 1, "up", "up_blocks")
    return self.output(x, self.config.out_channels)


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


# The two below run one image at a time (`lax.map`): at full resolution the VAE's activations
# are the largest of a whole sampling run, and this keeps them independent of the batch size.


def encode_to_latents(vae: AutoencoderKL, params: dict, images: jax.Array,
                      posterior_noise: jax.Array) -> jax.Array:
  """[N, H, W, C] images in [-1, 1] -> [N, h, w, latent] diffusion latents, sampling each
  image's posterior with its standard-normal noise [N, h, w, latent]."""

  def encode_one(image_and_noise):
    image, noise = image_and_noise
    posterior: DiagonalGaussian = vae.apply({"params": params}, image[None], method=vae.encode)
    return vae.config.to_diffusion_latents(posterior.sample_from_noise(noise[None]))[0]

  return jax.lax.map(encode_one, (images, posterior_noise))


def decode_from_latents(vae: AutoencoderKL, params: dict, latents: jax.Array) -> jax.Array:
  """[N, h, w, latent] diffusion latents -> [N, H, W, C] images in about [-1, 1]."""

  def decode_one(one_latents):
    z = vae.config.from_diffusion_latents(one_latents[None])
    return vae.apply({"params": params}, z, method=vae.decode)[0]

  return jax.lax.map(decode_one, latents)


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
             attention: AttentionOptions = AttentionOptions(), compute_dtype: Dtype = jnp.float32
             ) -> tuple[AutoencoderKL, dict]:
  """Builds the AutoencoderKL of a diffusers `vae/` directory and loads its safetensors.

  Arguments as `unet.load_unet`; `path` may be a pipeline directory containing `vae/`.
  """
  directory = model_configs.component_directory(path, "vae")
  config = model_configs.AutoencoderConfig.from_dict(model_configs.read_config(directory),
                                                     directory / "config.json")
  module = AutoencoderKL(config, attention, compute_dtype)
  return module, weights.load_params(module, directory, dtype, variant,
                                     rename=_rename_legacy_attention)
