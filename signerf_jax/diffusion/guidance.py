"""How the sampler's networks are conditioned and guided, as diffusers' inpainting pipelines do.

  * Classifier-free guidance runs the UNet on 2B rows, the unconditional (negative prompt) half
    first, and combines the two predictions: eps_uncond + guidance_scale * (eps_cond -
    eps_uncond). `text_conditioning` lays out the text rows, `classifier_free_guidance` combines.
  * The ControlNet takes the control image with its conditioning channels (`control_image`),
    embedded once per image rather than at every step (`embed_control`), and acts at
    `controlnet_conditioning_scale` in the steps between control_guidance_start and
    control_guidance_end (`controlnet_conditioning_scale_per_step`, diffusers' `controlnet_keep`).
`Guidance` carries the traced strengths into `sampler.sample`: new values reuse its compiled
program.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from signerf_jax.clip.text import PromptEmbeddings
from signerf_jax.diffusion import controlnet as controlnet_lib
from signerf_jax.errors import InputError


@struct.dataclass
class Guidance:
  """The traced guidance strengths.

  Attributes:
    guidance_scale: () float32 classifier-free guidance weight (used when
      `SamplerSettings.classifier_free_guidance`).
    controlnet_conditioning_scale: [S] float32, the ControlNet conditioning scale of each step
      run, zero where control guidance is off (`controlnet_conditioning_scale_per_step`).
  """
  guidance_scale: jax.Array
  controlnet_conditioning_scale: jax.Array


def controlnet_conditioning_scale_per_step(num_steps: int, controlnet_conditioning_scale: float,
                                           guidance_start: float = 0.0,
                                           guidance_end: float = 1.0) -> np.ndarray:
  """[num_steps] float32 ControlNet scale per step run, as diffusers' `controlnet_keep`.

  Step i (of the steps run, after strength truncation) is controlled unless
  i / S < guidance_start or (i + 1) / S > guidance_end.
  """
  if not 0.0 <= guidance_start < guidance_end <= 1.0:
    raise InputError(f"control guidance must satisfy 0 <= start < end <= 1, got start "
                     f"{guidance_start} and end {guidance_end}", field="control_guidance_start")
  keep = [1.0 - float(i / num_steps < guidance_start or (i + 1) / num_steps > guidance_end)
          for i in range(num_steps)]
  return (controlnet_conditioning_scale * np.asarray(keep)).astype(np.float32)


def text_conditioning(prompt: PromptEmbeddings, time_ids: jax.Array | None, batch: int,
                      guided: bool) -> tuple[jax.Array, jax.Array | None, jax.Array | None]:
  """(text states, pooled text embeds, time ids) for the UNet batch: [negative; positive] rows
  under guidance, each broadcast from 1 or B rows to B."""
  def rows(positive, negative):
    if positive is None:
      return None
    positive = jnp.broadcast_to(positive, (batch, *positive.shape[1:]))
    if not guided:
      return positive
    if negative is None:
      raise InputError("classifier-free guidance needs negative prompt embeddings (encode the "
                       "prompt with guidance=True)", field="negative_prompt_embeds")
    return jnp.concatenate([jnp.broadcast_to(negative, positive.shape), positive])
  return (rows(prompt.prompt_embeds, prompt.negative_prompt_embeds),
          rows(prompt.pooled_prompt_embeds, prompt.negative_pooled_prompt_embeds),
          rows(time_ids, time_ids))


def control_image(control: jax.Array, channels: int) -> jax.Array:
  """The [B, H, W, C] control image with the ControlNet's `channels` (a grey image is repeated,
  as PIL's convert("RGB") of the control image does in diffusers)."""
  if control.shape[-1] == 1 and channels != 1:
    control = jnp.repeat(control, channels, axis=-1)
  if control.shape[-1] != channels:
    raise InputError(f"control has {control.shape[-1]} channels but the ControlNet takes "
                     f"{channels}", field="control")
  return control


def embed_control(controlnet: controlnet_lib.ControlNet, params: dict, control: jax.Array
                  ) -> jax.Array:
  """The [B, h, w, E] conditioning embedding `controlnet` (with `params`) adds to its input
  convolution, of the control images [B, H, W, C or 1] in [0, 1] (`control_image`)."""
  return controlnet_lib.embed_conditioning(
      controlnet, params, control_image(control, controlnet.config.conditioning_channels))


def both_halves(x: jax.Array, guided: bool) -> jax.Array:
  """[B, ...] -> [x; x], the same rows for both halves of a guided batch (x without guidance)."""
  return jnp.concatenate([x, x]) if guided else x


def classifier_free_guidance(prediction: jax.Array, guidance_scale: jax.Array) -> jax.Array:
  """[2B, ...] predictions (unconditional half first) -> the [B, ...] guided prediction."""
  unconditional, conditional = jnp.split(prediction, 2)
  return unconditional + guidance_scale * (conditional - unconditional)
