"""diffusers' ControlNetModel in Flax (SD 1.x/2.x and the SDXL text_time variant).

Layout: latents and the conditioning image are NHWC. The conditioning image is in pixel space
([B, 8h, 8w, C] for h x w latents with the usual 4-stage embedding), in whatever range the
checkpoint was trained on (diffusers' pipelines feed [0, 1]). The output is a
`ControlNetResiduals` that `UNet2DCondition(..., control=...)` adds into its skips and mid block.

    module, params = load_controlnet("checkpoint/controlnet")
    residuals = jax.jit(module.apply, static_argnames="guess_mode")(
        {"params": params}, latents, timestep, text_states, depth_image, 1.0)

The conditioning embedding depends only on the conditioning image, so a sampler computes it once
per image (`embed_conditioning`) rather than at every step, and passes it in as
`conditioning_embedding`. It is convolutions and SiLUs alone: each latent cell depends on a
bounded patch of pixels (`conditioning_radius`), so where images differ only inside a rectangle
(a sheet whose slot alone changes) only the cells the rectangle reaches are recomputed
(`embed_conditioning_region`).
"""

from __future__ import annotations

import os

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from signerf_jax.diffusion import model_configs, weights
from signerf_jax.diffusion.attention import AttentionOptions
from signerf_jax.diffusion.blocks import Backbone, ControlNetResiduals
from signerf_jax.diffusion.layers import Conv2d, Dtype
from signerf_jax.errors import InputError


class ConditioningEmbedding(nn.Module):
  """The small conv net taking the conditioning image down to latent resolution.

  [B, H, W, conditioning_channels] -> [B, H / 2^(n-1), W / 2^(n-1), out_channels], n being the
  number of `block_out_channels`; its last convolution is zero-initialised in training.
  """
  out_channels: int
  block_out_channels: tuple[int, ...]
  compute_dtype: Dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    conv = lambda features, name, stride=1: Conv2d(features, stride=stride, name=name,
                                                   compute_dtype=self.compute_dtype)
    x = nn.silu(conv(self.block_out_channels[0], "conv_in")(x))
    for index, (channels, next_channels) in enumerate(zip(self.block_out_channels[:-1],
                                                          self.block_out_channels[1:])):
      x = nn.silu(conv(channels, f"blocks_{2 * index}")(x))
      x = nn.silu(conv(next_channels, f"blocks_{2 * index + 1}", stride=2)(x))
    return conv(self.out_channels, "conv_out")(x)

  @classmethod
  def of(cls, controlnet: "ControlNet", **module_options) -> "ConditioningEmbedding":
    """The embedding of `controlnet` (its configuration and compute dtype)."""
    config = controlnet.config
    return cls(config.block_out_channels[0], config.conditioning_embedding_out_channels,
               controlnet.compute_dtype, **module_options)


def conditioning_strides(config: model_configs.ControlNetConfig) -> list[int]:
  """The strides of `ConditioningEmbedding`'s 3 x 3, padding-1 convolutions, in order."""
  return [1] + [1, 2] * (len(config.conditioning_embedding_out_channels) - 1) + [1]


def conditioning_radius(config: model_configs.ControlNetConfig) -> int:
  """R, in pixels: latent cell i of the conditioning embedding (latent factor f) depends only
  on pixels f i - R .. f i + R of the conditioning image (along each axis; 11 for three
  embedding blocks: each 3 x 3 convolution reaches one cell of its input further)."""
  radius, spacing = 0, 1
  for stride in conditioning_strides(config):
    radius += spacing
    spacing *= stride
  return radius


def _conditioning_image(config: model_configs.ControlNetConfig,
                        controlnet_cond: jax.Array) -> jax.Array:
  """The conditioning image [B, H, W, C] checked and in the channel order the model takes."""
  if controlnet_cond.shape[-1] != config.conditioning_channels:
    raise InputError(f"controlnet_cond has {controlnet_cond.shape[-1]} channels (NHWC) but "
                     f"the ControlNet takes {config.conditioning_channels}",
                     field="controlnet_cond")
  return controlnet_cond[..., ::-1] if config.conditioning_channel_order == "bgr" else (
      controlnet_cond)


def embed_conditioning(controlnet: "ControlNet", params: dict,
                       controlnet_cond: jax.Array) -> jax.Array:
  """The conditioning embedding `controlnet` (with `params`) adds to its input convolution:
  [B, H, W, conditioning_channels] -> [B, H / f, W / f, block_out_channels[0]] (f the latent
  factor); pass it to `ControlNet.__call__` as `conditioning_embedding`."""
  return ConditioningEmbedding.of(controlnet).apply(
      {"params": params["controlnet_cond_embedding"]},
      _conditioning_image(controlnet.config, controlnet_cond))


def embed_conditioning_region(controlnet: "ControlNet", params: dict, embedding: jax.Array,
                              controlnet_cond: jax.Array, region: tuple[int, int, int, int]
                              ) -> jax.Array:
  """The conditioning embedding of `controlnet_cond` from `embedding`, that of images equal to
  it outside the pixel rectangle `region`, recomputing only the cells the rectangle reaches.

  Exact (to float rounding): a cell within `conditioning_radius` pixels of the rectangle is
  recomputed from a window holding every pixel it depends on (the window's edges are image
  edges or at least that far from it); every other cell depends on no pixel inside it.

  Args:
    embedding: [1 or B, h, w, E] the embedding of the images `controlnet_cond` differs from.
    controlnet_cond: [B, H, W, C] the new conditioning images (H = f h, W = f w).
    region: (top, left, height, width) in pixels: where `controlnet_cond` may differ.
  Returns:
    [B, h, w, E].
  """
  factor = 2 ** (len(controlnet.config.conditioning_embedding_out_channels) - 1)
  reach = -(-conditioning_radius(controlnet.config) // factor)  # In cells.
  top, left, height, width = region
  batch, cells = controlnet_cond.shape[0], embedding.shape[1:3]
  # The cells to recompute, [start, stop) per axis, and the window they are computed from.
  starts = [max(start // factor - reach, 0) for start in (top, left)]
  stops = [min(-(-(start + size) // factor) + reach, count)
           for start, size, count in zip((top, left), (height, width), cells)]
  window_starts = [max(start - reach, 0) for start in starts]
  window_stops = [min(stop + reach, count) for stop, count in zip(stops, cells)]
  window = controlnet_cond[:, window_starts[0] * factor:window_stops[0] * factor,
                           window_starts[1] * factor:window_stops[1] * factor]
  recomputed = embed_conditioning(controlnet, params, window)[
      :, starts[0] - window_starts[0]:stops[0] - window_starts[0],
      starts[1] - window_starts[1]:stops[1] - window_starts[1]]
  embedding = jnp.broadcast_to(embedding, (batch, *embedding.shape[1:]))
  return embedding.at[:, starts[0]:stops[0], starts[1]:stops[1]].set(recomputed)


def guess_mode_scales(count: int) -> np.ndarray:
  """diffusers' guess-mode weights: 10^linspace(-1, 0, count), from 0.1 (shallowest) to 1 (mid)."""
  return np.logspace(-1.0, 0.0, count).astype(np.float32)


def scale_residuals(down: list[jax.Array], mid: jax.Array,
                    controlnet_conditioning_scale: float | jax.Array, guess_mode: bool,
                    global_pool_conditions: bool) -> ControlNetResiduals:
  """The zero convolutions' outputs times the conditioning scale, as diffusers weights them.

  In guess mode (without pooled conditions) the scale is weighted from 0.1 at the shallowest
  skip to 1 at the mid block (`guess_mode_scales`); pooled conditions are then averaged over
  height and width ([B, 1, 1, C]).
  """
  if guess_mode and not global_pool_conditions:
    residual_scales = (jnp.asarray(guess_mode_scales(len(down) + 1))
                       * controlnet_conditioning_scale)
  else:
    residual_scales = jnp.broadcast_to(
        jnp.asarray(controlnet_conditioning_scale, jnp.float32), (len(down) + 1,))
  down = [residual * residual_scales[index] for index, residual in enumerate(down)]
  mid = mid * residual_scales[-1]
  if global_pool_conditions:
    down = [jnp.mean(residual, axis=(1, 2), keepdims=True) for residual in down]
    mid = jnp.mean(mid, axis=(1, 2), keepdims=True)
  return ControlNetResiduals(tuple(down), mid)


class ControlNet(Backbone):
  """ControlNetModel; configure it with `ControlNetConfig.from_dict(config_json)`."""
  config: model_configs.ControlNetConfig

  @nn.compact
  def __call__(self, sample: jax.Array, timesteps: jax.Array, encoder_hidden_states: jax.Array,
               controlnet_cond: jax.Array | None,
               controlnet_conditioning_scale: float | jax.Array = 1.0, *,
               guess_mode: bool = False, text_embeds: jax.Array | None = None,
               time_ids: jax.Array | None = None,
               conditioning_embedding: jax.Array | None = None) -> ControlNetResiduals:
    """Computes the residuals for the UNet.

    Args:
      sample: [B, h, w, in_channels] NHWC latents (as fed to the UNet, without inpainting
        channels for a 4-channel ControlNet).
      timesteps: scalar or [B].
      encoder_hidden_states: [B, S, cross_attention_dim].
      controlnet_cond: [B, H, W, conditioning_channels] NHWC conditioning image, RGB order
        (flipped here for checkpoints trained on BGR).
      controlnet_conditioning_scale: multiplies every residual (diffusers' ControlNetModel calls
        it conditioning_scale); may be a traced scalar (no recompilation).
      guess_mode: weight residuals from 0.1 (shallowest skip) to 1.0 (mid block) as diffusers
        does; a Python bool (it is part of the compiled program).
      text_embeds, time_ids: SDXL's text_time conditioning.
      conditioning_embedding: [B, h, w, block_out_channels[0]], `embed_conditioning` of
        `controlnet_cond` computed already (then `controlnet_cond` may be None).

    Returns:
      ControlNetResiduals with one down map per UNet skip and the mid map; with
      global_pool_conditions each map is averaged over height and width ([B, 1, 1, C]).
    """
    config = self.config
    if conditioning_embedding is None:
      conditioning_embedding = ConditioningEmbedding.of(self, name="controlnet_cond_embedding")(
          _conditioning_image(config, controlnet_cond))
    time_embedding = self.embed_time(timesteps, sample.shape[0], text_embeds, time_ids)
    context = encoder_hidden_states
    x = self.input_convolution(sample) + conditioning_embedding
    x, skips = self.down_path(x, time_embedding, context)
    x = self.middle(x, time_embedding, context)
    zero_conv = lambda skip, name: Conv2d(skip.shape[-1], kernel_size=1, padding=0, name=name,
                                          compute_dtype=self.compute_dtype)(skip)
    down = [zero_conv(skip, f"controlnet_down_blocks_{index}") for index, skip in enumerate(skips)]
    mid = zero_conv(x, "controlnet_mid_block")
    return scale_residuals(down, mid, controlnet_conditioning_scale, guess_mode,
                           config.global_pool_conditions)

  def example_inputs(self) -> dict[str, jax.ShapeDtypeStruct]:
    """Abstract inputs of the smallest valid size, for shape inference (`weights`)."""
    inputs = super().example_inputs()
    batch, size = inputs["sample"].shape[:2]
    image_size = size * 2 ** (len(self.config.conditioning_embedding_out_channels) - 1)
    inputs["controlnet_cond"] = jax.ShapeDtypeStruct(
        (batch, image_size, image_size, self.config.conditioning_channels), jnp.float32)
    return inputs


def load_controlnet(path: str | os.PathLike, dtype=np.float32, *, variant: str | None = None,
                    attention: AttentionOptions = AttentionOptions(),
                    compute_dtype: Dtype = jnp.float32) -> tuple[ControlNet, dict]:
  """Builds the ControlNet of a diffusers `controlnet/` directory and loads its safetensors.

  Arguments as `unet.load_unet`; `path` may be a pipeline directory containing `controlnet/`.
  """
  directory = model_configs.component_directory(path, "controlnet")
  config = model_configs.ControlNetConfig.from_dict(model_configs.read_config(directory),
                                                    directory / "config.json")
  module = ControlNet(config, attention, compute_dtype)
  return module, weights.load_params(module, directory, dtype, variant)
