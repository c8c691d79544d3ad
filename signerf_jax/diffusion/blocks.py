"""The UNet's down, mid and up blocks and its time embedding, shared with the ControlNet.

Blocks take the parsed config and their index and derive channels, heads and layer counts
exactly as diffusers' `get_down_block` / `get_mid_block` / `get_up_block` calls do. Input
channel counts are never configured: Flax infers them from the arrays, so skip concatenations
need no bookkeeping. Layout is NHWC throughout (see `layers`).
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

from signerf_jax.diffusion import model_configs
from signerf_jax.diffusion.attention import AttentionOptions, Transformer2D
from signerf_jax.diffusion.layers import (Downsample2D, Dtype, ResnetBlock2D, TimestepEmbedding,
                                          Upsample2D, timestep_embedding)
from signerf_jax.errors import InputError


@struct.dataclass
class ControlNetResiduals:
  """What a ControlNet adds into a UNet, already multiplied by the conditioning scale.

  Attributes:
    down: one NHWC map per UNet skip connection, in the order the down path produces them
      (conv_in output first); shapes equal the UNet's skips.
    mid: the NHWC map added to the mid-block output.
  """
  down: tuple[jax.Array, ...]
  mid: jax.Array


def embed_time(config: model_configs.BackboneConfig, timesteps: jax.Array, batch: int,
               text_embeds: jax.Array | None, time_ids: jax.Array | None,
               compute_dtype: Dtype) -> jax.Array:
  """The [B, time_embedding_dim] embedding of the timesteps (plus SDXL's text_time embedding).

  Must be called inside the compact method of the UNet or ControlNet: it creates their
  `time_embedding` and `add_embedding` submodules.

  Args:
    timesteps: scalar or [B] (integer or float) diffusion timesteps.
    text_embeds: [B, pooled_dim] pooled text embedding (SDXL only).
    time_ids: [B, 6] original size, crop offset and target size (SDXL only).
  """
  timesteps = jnp.broadcast_to(jnp.reshape(jnp.asarray(timesteps, jnp.float32), (-1,)), (batch,))
  sinusoid = timestep_embedding(timesteps, config.block_out_channels[0], config.flip_sin_to_cos,
                                config.freq_shift)
  embedding = TimestepEmbedding(config.time_embedding_dim, compute_dtype,
                                name="time_embedding")(sinusoid)
  if config.addition_embed_type == "text_time":
    if text_embeds is None or time_ids is None:
      raise InputError("this model (addition_embed_type 'text_time', SDXL) needs text_embeds "
                       "and time_ids", field="text_embeds" if text_embeds is None else "time_ids")
    time_ids_embedding = timestep_embedding(
        jnp.reshape(time_ids, (-1,)), config.addition_time_embed_dim, config.flip_sin_to_cos,
        config.freq_shift).reshape(batch, -1)
    added = jnp.concatenate([text_embeds.astype(jnp.float32), time_ids_embedding], axis=-1)
    embedding = embedding + TimestepEmbedding(config.time_embedding_dim, compute_dtype,
                                              name="add_embedding")(added)
  return embedding


def example_inputs(config: model_configs.BackboneConfig, batch: int = 1
                   ) -> dict[str, jax.ShapeDtypeStruct]:
  """Abstract UNet/ControlNet inputs of the smallest valid size (for shape inference)."""
  size = 2 ** (len(config.block_out_channels) - 1)
  inputs = dict(sample=jax.ShapeDtypeStruct((batch, size, size, config.in_channels), jnp.float32),
                timesteps=jax.ShapeDtypeStruct((batch,), jnp.float32),
                encoder_hidden_states=jax.ShapeDtypeStruct(
                    (batch, 1, config.cross_attention_dim), jnp.float32))
  if config.addition_embed_type == "text_time":
    pooled = config.projection_class_embeddings_input_dim - 6 * config.addition_time_embed_dim
    inputs["text_embeds"] = jax.ShapeDtypeStruct((batch, pooled), jnp.float32)
    inputs["time_ids"] = jax.ShapeDtypeStruct((batch, 6), jnp.float32)
  return inputs


class _BlockBase(nn.Module):
  config: model_configs.BackboneConfig
  index: int
  attention: AttentionOptions = AttentionOptions()
  compute_dtype: Dtype = jnp.float32

  def resnet(self, name: str, out_channels: int, scale: float = 1.0) -> ResnetBlock2D:
    return ResnetBlock2D(out_channels, self.config.norm_num_groups, self.config.norm_eps, scale,
                         self.compute_dtype, name=name)

  def transformer(self, name: str, channels: int, heads: int, layers: int) -> Transformer2D:
    return Transformer2D(heads, channels // heads, layers, self.config.norm_num_groups,
                         self.config.use_linear_projection, self.attention, self.compute_dtype,
                         name=name)


class DownBlock(_BlockBase):
  """CrossAttnDownBlock2D or DownBlock2D number `index`.

  x [B, H, W, C_in] -> (x [B, H', W', C], skips): one skip per resnet layer, plus the
  downsampled map when the block downsamples (all but the last block).
  """

  @nn.compact
  def __call__(self, x: jax.Array, time_embedding: jax.Array, context: jax.Array
               ) -> tuple[jax.Array, tuple[jax.Array, ...]]:
    config, index = self.config, self.index
    channels = config.block_out_channels[index]
    has_attention = config.down_block_types[index] == model_configs.CROSS_ATTENTION_DOWN
    skips = []
    for layer in range(config.layers_per_block[index]):
      x = self.resnet(f"resnets_{layer}", channels)(x, time_embedding)
      if has_attention:
        x = self.transformer(f"attentions_{layer}", channels, config.num_attention_heads[index],
                             config.transformer_layers_per_block[index])(x, context)
      skips.append(x)
    if index < len(config.block_out_channels) - 1:
      x = Downsample2D(channels, config.downsample_padding, self.compute_dtype,
                       name="downsamplers_0")(x)
      skips.append(x)
    return x, tuple(skips)


class MidBlock(_BlockBase):
  """UNetMidBlock2DCrossAttn (resnet, transformer, resnet) or UNetMidBlock2D (one resnet).

  It takes the per-block settings of the last down block (index -1), as diffusers does.
  """
  index: int = -1

  @nn.compact
  def __call__(self, x: jax.Array, time_embedding: jax.Array, context: jax.Array) -> jax.Array:
    config, index = self.config, self.index
    channels = config.block_out_channels[index]
    scale = config.mid_block_scale_factor
    x = self.resnet("resnets_0", channels, scale)(x, time_embedding)
    if config.mid_block_type == model_configs.CROSS_ATTENTION_MID:
      x = self.transformer("attentions_0", channels, config.num_attention_heads[index],
                           config.transformer_layers_per_block[index])(x, context)
      x = self.resnet("resnets_1", channels, scale)(x, time_embedding)
    return x


class UpBlock(_BlockBase):
  """CrossAttnUpBlock2D or UpBlock2D number `index` of the up path (deepest first).

  Consumes its skips last-first, concatenating each onto the channels before a resnet, and
  upsamples to `upsample_size` (the next skip's height, width) unless it is the last block.
  """
  config: model_configs.UNetConfig

  @nn.compact
  def __call__(self, x: jax.Array, skips: tuple[jax.Array, ...], time_embedding: jax.Array,
               context: jax.Array, upsample_size: tuple[int, int] | None) -> jax.Array:
    config, index = self.config, self.index
    block = len(config.block_out_channels) - 1 - index  # the matching down block
    channels = config.block_out_channels[block]
    has_attention = config.up_block_types[index] == model_configs.CROSS_ATTENTION_UP
    for layer, skip in enumerate(reversed(skips)):
      x = jnp.concatenate([x, skip], axis=-1)
      x = self.resnet(f"resnets_{layer}", channels)(x, time_embedding)
      if has_attention:
        x = self.transformer(f"attentions_{layer}", channels, config.num_attention_heads[block],
                             config.transformer_layers_per_block[block])(x, context)
    if upsample_size is not None:
      x = Upsample2D(channels, self.compute_dtype, name="upsamplers_0")(x, upsample_size)
    return x
