"""diffusers' UNet2DConditionModel in Flax (SD 1.x, SD 2.x, SDXL; 4- or 9-channel input).

Layout: `sample` and the output are NHWC latents [B, H, W, C] (diffusers uses NCHW; transpose
with `x.transpose(0, 2, 3, 1)` at the boundary). `encoder_hidden_states` is [B, S, D] as in
diffusers. ControlNet residuals enter as a `ControlNetResiduals` (NHWC maps) and are added to
the skips and to the mid-block output exactly where diffusers adds them.

    module, params = load_unet("checkpoint/unet")
    apply = jax.jit(module.apply)
    noise_prediction = apply({"params": params}, latents, timestep, text_states)
"""

from __future__ import annotations

import os

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from signerf_jax.diffusion import model_configs, weights
from signerf_jax.diffusion.attention import AttentionOptions
from signerf_jax.diffusion.blocks import Backbone, ControlNetResiduals, UpBlock
from signerf_jax.diffusion.layers import Conv2d, Dtype, GroupNorm
from signerf_jax.errors import InputError


class UNet2DCondition(Backbone):
  """The denoising UNet; configure it with `UNetConfig.from_dict(config_json)`."""
  config: model_configs.UNetConfig

  @nn.compact
  def __call__(self, sample: jax.Array, timesteps: jax.Array, encoder_hidden_states: jax.Array,
               *, text_embeds: jax.Array | None = None, time_ids: jax.Array | None = None,
               control: ControlNetResiduals | None = None) -> jax.Array:
    """Predicts noise (or v) for a batch of latents.

    Args:
      sample: [B, H, W, in_channels] NHWC latents (inpainting UNets: 9 channels = latents,
        mask, masked-image latents, concatenated in that order as diffusers does).
      timesteps: scalar or [B] diffusion timesteps.
      encoder_hidden_states: [B, S, cross_attention_dim] text-encoder states.
      text_embeds: [B, pooled_dim] pooled text embedding (SDXL's text_time conditioning).
      time_ids: [B, 6] SDXL size/crop conditioning.
      control: ControlNet residuals, or None.

    Returns:
      [B, H, W, out_channels] float32.
    """
    config = self.config
    if sample.shape[-1] != config.in_channels:
      raise InputError(f"sample has {sample.shape[-1]} channels (NHWC) but the UNet takes "
                       f"{config.in_channels}", field="sample")
    if config.center_input_sample:
      sample = 2 * sample - 1.0
    time_embedding = self.embed_time(timesteps, sample.shape[0], text_embeds, time_ids)
    context = encoder_hidden_states
    x, skips = self.down_path(self.input_convolution(sample), time_embedding, context)
    if control is not None:
      if len(control.down) != len(skips):
        raise InputError(f"{len(control.down)} down residuals for {len(skips)} UNet skips",
                         field="control")
      skips = [skip + residual for skip, residual in zip(skips, control.down)]
    if config.mid_block_type is not None:
      x = self.middle(x, time_embedding, context)
    if control is not None:
      x = x + control.mid
    x = self.up_path(x, skips, time_embedding, context)
    x = nn.silu(GroupNorm(config.norm_num_groups, config.norm_eps, name="conv_norm_out")(x))
    return Conv2d(config.out_channels, config.conv_out_kernel, padding=config.conv_out_kernel // 2,
                  compute_dtype=self.compute_dtype, name="conv_out")(x)

  def up_path(self, x: jax.Array, skips: list[jax.Array], time_embedding: jax.Array,
              context: jax.Array) -> jax.Array:
    """The up blocks (deepest first), each consuming its skips and upsampling to the size of
    the skip before them."""
    config = self.config
    last = len(config.block_out_channels) - 1
    for index in range(len(config.block_out_channels)):
      count = config.layers_per_block[last - index] + 1
      block_skips, skips = skips[-count:], skips[:-count]
      upsample_size = skips[-1].shape[1:3] if index < last else None
      x = UpBlock(config, index, self.attention, self.compute_dtype, name=f"up_blocks_{index}")(
          x, tuple(block_skips), time_embedding, context, upsample_size)
    return x


def load_unet(path: str | os.PathLike, dtype=np.float32, *, variant: str | None = None,
              attention: AttentionOptions = AttentionOptions(), compute_dtype: Dtype = jnp.float32
              ) -> tuple[UNet2DCondition, dict]:
  """Builds the UNet described by a diffusers `unet/` directory and loads its safetensors.

  Args:
    path: the `unet` component directory, or a pipeline directory containing `unet/`.
    dtype: dtype the parameters are stored in (fp16/bf16 checkpoints are converted exactly).
    variant: diffusers weight variant ("fp16" picks diffusion_pytorch_model.fp16.safetensors).
    attention: attention evaluation options.
    compute_dtype: float32, or bfloat16 for bf16 matmuls/convolutions with float32 accumulation.

  Returns:
    (module, params): call `module.apply({"params": params}, ...)`.
  """
  directory = model_configs.component_directory(path, "unet")
  config = model_configs.UNetConfig.from_dict(model_configs.read_config(directory),
                                              directory / "config.json")
  module = UNet2DCondition(config, attention, compute_dtype)
  return module, weights.load_params(module, directory, dtype, variant)
