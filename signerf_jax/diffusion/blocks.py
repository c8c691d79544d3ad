"""The UNet's down, mid and up blocks and its time embedding, shared with the ControlNet.

Blocks take the parsed config and their index and derive channels, heads and layer counts
exactly as diffusers' `get_down_block` / `get_mid_block` / `get_up_block` calls do. Input
channel counts are never configured: Flax infers them from the arrays, so skip concatenations
need no bookkeeping. Layout is NHWC throughout (see `layers`).

`Backbone` is what the UNet and the ControlNet have in common: the time embedding (with SDXL's
text_time conditioning), the input convolution, and the down path with its mid block.
"""

from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

from signerf_jax.diffusion import model_configs, model_options
from signerf_jax.diffusion.attention import AttentionOptions, Transformer2D
from signerf_jax.diffusion.layers import Conv2d, Dtype, Linear
from signerf_jax.diffusion.resnet import Downsample2D, ResnetBlock2D, Upsample2D
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


def timestep_embedding(timesteps: jax.Array, dim: int, flip_sin_to_cos: bool, freq_shift: float,
                       max_period: float = 10000.0) -> jax.Array:
  """Sinusoidal embedding of [N] timesteps -> [N, dim] float32 (get_timestep_embedding)."""
  half = dim // 2
  exponent = -math.log(max_period) * jnp.arange(half, dtype=jnp.float32) / (half - freq_shift)
  angles = jnp.asarray(timesteps, jnp.float32)[:, None] * jnp.exp(exponent)[None, :]
  sin, cos = jnp.sin(angles), jnp.cos(angles)
  embedding = jnp.concatenate([cos, sin] if flip_sin_to_cos else [sin, cos], axis=-1)
  if dim % 2:
    embedding = jnp.pad(embedding, ((0, 0), (0, 1)))
  return embedding


class TimestepEmbedding(nn.Module):
  """linear_1 -> SiLU -> linear_2 (diffusers' TimestepEmbedding)."""
  features: int
  compute_dtype: Dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    x = nn.silu(Linear(self.features, name="linear_1", compute_dtype=self.compute_dtype)(x))
    return Linear(self.features, name="linear_2", compute_dtype=self.compute_dtype)(x)


class _BlockBase(nn.Module):
  """A down, mid or up block: its config and index, and the layers it stacks."""
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
    has_attention = config.down_block_types[index] == model_options.CROSS_ATTENTION_DOWN
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
    if config.mid_block_type == model_options.CROSS_ATTENTION_MID:
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
    has_attention = config.up_block_types[index] == model_options.CROSS_ATTENTION_UP
    for layer, skip in enumerate(reversed(skips)):
      x = jnp.concatenate([x, skip], axis=-1)
      x = self.resnet(f"resnets_{layer}", channels)(x, time_embedding)
      if has_attention:
        x = self.transformer(f"attentions_{layer}", channels, config.num_attention_heads[block],
                             config.transformer_layers_per_block[block])(x, context)
    if upsample_size is not None:
      x = Upsample2D(channels, self.compute_dtype, name="upsamplers_0")(x, upsample_size)
    return x


class Backbone(nn.Module):
  """The encoder half of the UNet and the ControlNet (configured by their `BackboneConfig`).

  Its methods create submodules under diffusers' names (time_embedding, add_embedding, conv_in,
  down_blocks_<i>, mid_block; the methods' own names differ, as Flax requires), so a subclass
  calls them from its compact `__call__`.
  """
  config: model_configs.BackboneConfig
  attention: AttentionOptions = AttentionOptions()
  compute_dtype: Dtype = jnp.float32

  def embed_time(self, timesteps: jax.Array, batch: int, text_embeds: jax.Array | None,
                 time_ids: jax.Array | None) -> jax.Array:
    """The [B, time_embedding_dim] embedding of the timesteps (plus SDXL's text_time embedding).

    Args:
      timesteps: scalar or [B] (integer or float) diffusion timesteps.
      text_embeds: [B, pooled_dim] pooled text embedding (SDXL only).
      time_ids: [B, 6] original size, crop offset and target size (SDXL only).
    """
    config, compute_dtype = self.config, self.compute_dtype
    timesteps = jnp.broadcast_to(jnp.reshape(jnp.asarray(timesteps, jnp.float32), (-1,)),
                                 (batch,))
    sinusoid = timestep_embedding(timesteps, config.block_out_channels[0],
                                  config.flip_sin_to_cos, config.freq_shift)
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

  def input_convolution(self, sample: jax.Array) -> jax.Array:
    """conv_in: [B, H, W, in_channels] latents -> [B, H, W, block_out_channels[0]]."""
    config = self.config
    return Conv2d(config.block_out_channels[0], config.conv_in_kernel,
                  padding=config.conv_in_kernel // 2, compute_dtype=self.compute_dtype,
                  name="conv_in")(sample)

  def down_path(self, x: jax.Array, time_embedding: jax.Array, context: jax.Array
                ) -> tuple[jax.Array, list[jax.Array]]:
    """conv_in's output -> (the deepest map, the skips: x first, then each down block's)."""
    skips = [x]
    for index in range(len(self.config.block_out_channels)):
      x, block_skips = DownBlock(self.config, index, self.attention, self.compute_dtype,
                                 name=f"down_blocks_{index}")(x, time_embedding, context)
      skips.extend(block_skips)
    return x, skips

  def middle(self, x: jax.Array, time_embedding: jax.Array, context: jax.Array) -> jax.Array:
    """The mid block, on the deepest map of the down path."""
    return MidBlock(self.config, attention=self.attention, compute_dtype=self.compute_dtype,
                    name="mid_block")(x, time_embedding, context)

  def example_inputs(self) -> dict[str, jax.ShapeDtypeStruct]:
    """Abstract inputs of the smallest valid size, for shape inference (`weights`)."""
    config, batch = self.config, 1
    size = 2 ** (len(config.block_out_channels) - 1)
    inputs = dict(
        sample=jax.ShapeDtypeStruct((batch, size, size, config.in_channels), jnp.float32),
        timesteps=jax.ShapeDtypeStruct((batch,), jnp.float32),
        encoder_hidden_states=jax.ShapeDtypeStruct((batch, 1, config.cross_attention_dim),
                                                   jnp.float32))
    if config.addition_embed_type == "text_time":
      pooled = config.projection_class_embeddings_input_dim - 6 * config.addition_time_embed_dim
      inputs["text_embeds"] = jax.ShapeDtypeStruct((batch, pooled), jnp.float32)
      inputs["time_ids"] = jax.ShapeDtypeStruct((batch, 6), jnp.float32)
    return inputs
