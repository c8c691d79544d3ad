"""The compiled ControlNet inpainting sampler: diffusers' inpainting loop as one XLA program.

`sample` runs what diffusers' `StableDiffusionControlNetInpaintPipeline` and
`StableDiffusionXLControlNetInpaintPipeline` do between preprocessing the inputs and
post-processing the output, in one `jit`: mask binarisation and downsampling, VAE encoding of the
image and the masked image, the initial latents (`prepare_latents`, including img2img strength),
the whole denoising loop under `lax.scan`, VAE decoding and an optional paste-back. The loop
carries only the latents and the solver state, so no per-step activation outlives its step.

What each step computes (B samples; "2B" under classifier-free guidance, unconditional half first):
  * UNet input: the scheduler-scaled latents, and for a 9-channel inpainting UNet the
    downsampled mask and the masked image's latents concatenated after them (channels 4 + 1 + 4);
  * ControlNet residuals at scale `controlnet_conditioning_scale * keep[step]` (diffusers'
    `controlnet_keep` from control_guidance_start/end); in guess mode under guidance the
    ControlNet sees only the conditional half and the unconditional half gets zero residuals, as
    diffusers does;
  * guidance: eps_uncond + guidance_scale * (eps_cond - eps_uncond);
  * the scheduler step; for a 4-channel UNet, latent blending: outside the mask the latents are
    replaced by the original image's latents re-noised to the next step's level
    (diffusers' `init_latents_proper`), after the last step by the clean latents.

Static (part of the compiled program): the models' architectures, input shapes and batch size,
the number of steps run, the scheduler kind and `SamplerSettings` (guidance on/off, guess mode,
start from the image or from noise, paste-back and its blur radius). Traced (new values reuse the
compiled program): all parameters, prompt embeddings, SDXL time ids, images, masks, control
images, noise, `guidance_scale`, the per-step ControlNet scales and the schedule's arrays.

Batching: every per-sample input leads with the batch axis B (images, masks, control images,
every noise field; prompt embeddings and time ids have B rows or one shared row), and sample b
depends only on row b of each. So a batch of views is one call; `jax.vmap` over a further
leading axis (in_axes 0 for the per-sample inputs, None for models, schedule, guidance and
settings) gives the same as flattening it into B, and `shard_map` can split B across devices.
Noise drawn by `draw_noise` from per-sample keys keeps the property: a batch with keys
(k0, k1) equals two single-sample calls with k0 and k1.

Numerical conventions that match diffusers exactly:
  * mask preprocessing (`VaeImageProcessor(do_binarize=True)`): m < 0.5 -> 0, else 1, at pixel
    resolution; the masked image is image * (m < 0.5);
  * the latent mask: `torch.nn.functional.interpolate(mask, size=latent_size)` (mode "nearest",
    source index floor(i * in / out) in float32), see `downsample_mask`;
  * images in [0, 1] are mapped to [-1, 1] for the VAE and decoded images back with
    clip(x / 2 + 1 / 2, 0, 1); the ControlNet takes the control image in [0, 1];
  * VAE latents: z ~ posterior (a sample, with injected or key-drawn noise, as diffusers'
    `retrieve_latents` samples it), latents = (z - shift_factor) * scaling_factor. diffusers'
    Stable Diffusion pipelines ignore `shift_factor`; it is None (0) for every SD / SDXL VAE.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from signerf_jax.clip.text import PromptEmbeddings
from signerf_jax.diffusion.controlnet import ControlNet
from signerf_jax.diffusion.schedulers import Schedule
from signerf_jax.diffusion.unet import UNet2DCondition
from signerf_jax.diffusion.vae import AutoencoderKL, DiagonalGaussian
from signerf_jax.errors import InputError

BLUR_PASSES = 3  # PIL's GaussianBlur: three box blurs per axis.


@struct.dataclass
class DiffusionModels:
  """The networks of an inpainting pipeline with their parameters (a pytree; modules static).

  Attributes:
    unet: a 4-channel UNet (inpainting by latent blending) or an inpainting UNet with
      2 * latent_channels + 1 inputs (latents, mask, masked-image latents).
    vae: the AutoencoderKL.
    controlnet: the ControlNet, or None for plain inpainting.
    unet_params, vae_params, controlnet_params: their Flax parameters (None without ControlNet).
  """
  unet_params: dict
  vae_params: dict
  controlnet_params: dict | None
  unet: UNet2DCondition = struct.field(pytree_node=False)
  vae: AutoencoderKL = struct.field(pytree_node=False)
  controlnet: ControlNet | None = struct.field(pytree_node=False, default=None)

  def __post_init__(self):
    latent, unet_in = self.vae.config.latent_channels, self.unet.config.in_channels
    if unet_in not in (latent, 2 * latent + 1):
      raise InputError(f"the UNet takes {unet_in} input channels; an inpainting pipeline needs "
                       f"{latent} (latent blending) or {2 * latent + 1} (inpainting UNet) for a "
                       f"VAE with {latent} latent channels", field="unet.in_channels")
    if self.unet.config.out_channels != latent:
      raise InputError(f"the UNet predicts {self.unet.config.out_channels} channels but the VAE "
                       f"has {latent} latent channels", field="unet.out_channels")

  @property
  def latent_factor(self) -> int:
    """Pixels per latent cell along each axis: 2^(VAE blocks - 1) (8 for SD and SDXL)."""
    return 2 ** (len(self.vae.config.block_out_channels) - 1)

  @property
  def latent_channels(self) -> int:
    return self.vae.config.latent_channels

  @property
  def inpainting_unet(self) -> bool:
    """Whether the UNet takes the mask and masked-image latents (else: latent blending)."""
    return self.unet.config.in_channels != self.latent_channels


@struct.dataclass
class InpaintingInputs:
  """What to inpaint, per sample (H, W multiples of the latent factor).

  Attributes:
    image: [B, H, W, 3] float32 in [0, 1], the image to inpaint.
    mask: [B, H, W, 1] float32 in [0, 1]; >= 0.5 is regenerated, < 0.5 kept. A soft mask is
      binarised for the diffusion model and used as is (optionally blurred) for the paste-back.
    control: [B, H, W, C] float32 in [0, 1], the ControlNet's conditioning image (C = its
      conditioning channels, or 1 for a grey image broadcast to them), or None without ControlNet.
  """
  image: jax.Array
  mask: jax.Array
  control: jax.Array | None = None


@struct.dataclass
class SamplerNoise:
  """Every standard-normal draw of a run, per sample (h, w = H, W / latent factor, C latent).

  diffusers' inpainting pipelines draw these from their generator in the order image_posterior
  (only when used), latents, masked_image_posterior (always), then one `steps` entry per step
  (ancestral schedulers only), each over the whole batch in NCHW layout.

  Attributes:
    latents: [B, h, w, C], the initial noise (diffusers' `noise` in `prepare_latents`; also what
      latent blending re-noises the original with).
    image_posterior: [B, h, w, C], the posterior sample of the image's latents (used when
      starting from the image, strength < 1, and by latent blending).
    masked_image_posterior: [B, h, w, C], the posterior sample of the masked image's latents
      (used by inpainting UNets).
    steps: [B, S, h, w, C], fresh noise for each of the S steps (used by ancestral samplers).
  """
  latents: jax.Array
  image_posterior: jax.Array
  masked_image_posterior: jax.Array
  steps: jax.Array


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


@dataclasses.dataclass(frozen=True)
class SamplerSettings:
  """The static choices of a run (each combination is its own compiled program).

  Attributes:
    classifier_free_guidance: run the unconditional and conditional halves (diffusers: when
      guidance_scale > 1).
    guess_mode: ControlNet guess mode (residuals weighted 0.1 .. 1; under guidance only the
      conditional half gets them).
    start_from_image: strength < 1: start from the image's latents noised to the first step's
      level; otherwise from pure noise scaled by `init_noise_sigma`.
    paste_back: composite the output over the input image through the (blurred) mask.
    mask_blur: PIL GaussianBlur radius (pixels) applied to the mask for the paste-back; 0 = none.
  """
  classifier_free_guidance: bool = True
  guess_mode: bool = False
  start_from_image: bool = False
  paste_back: bool = False
  mask_blur: float = 0.0


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


@functools.partial(jax.jit, static_argnames=("latent_shape", "num_steps"))
def draw_noise(keys: jax.Array, latent_shape: tuple[int, int, int], num_steps: int
               ) -> SamplerNoise:
  """Standard-normal `SamplerNoise` from one PRNG key per sample.

  Args:
    keys: [B] PRNG keys; sample b's noise depends only on keys[b].
    latent_shape: (h, w, C).
    num_steps: S, the steps run.
  """
  def one_sample(key):
    latents_key, image_key, masked_image_key, steps_key = jax.random.split(key, 4)
    normal = lambda k, shape: jax.random.normal(k, shape, jnp.float32)
    return SamplerNoise(latents=normal(latents_key, latent_shape),
                        image_posterior=normal(image_key, latent_shape),
                        masked_image_posterior=normal(masked_image_key, latent_shape),
                        steps=normal(steps_key, (num_steps, *latent_shape)))
  return jax.vmap(one_sample)(keys)


# ----------------------------------------------------------------------------------------------
# Mask processing.


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


# ----------------------------------------------------------------------------------------------
# The sampler.


@struct.dataclass
class _LoopConstants:
  """What every step reads (no step writes it). Text fields are 2B long under guidance."""
  text_states: jax.Array
  text_embeds: jax.Array | None
  time_ids: jax.Array | None
  control: jax.Array | None  # [B, H, W, C] in [0, 1].
  mask: jax.Array  # [B, h, w, 1] binary.
  masked_image_latents: jax.Array | None  # Inpainting UNets.
  image_latents: jax.Array | None  # Latent blending.
  initial_noise: jax.Array


# The VAE runs on one image at a time (`lax.map`): at full resolution its activations are the
# largest of the whole run, and this keeps them independent of the batch size.


def _encode(models: DiffusionModels, images: jax.Array, posterior_noise: jax.Array) -> jax.Array:
  """[N, H, W, 3] images in [-1, 1] -> diffusion latents, sampling the posterior with the noise."""
  vae = models.vae

  def encode_one(image_and_noise):
    image, noise = image_and_noise
    posterior: DiagonalGaussian = vae.apply({"params": models.vae_params}, image[None],
                                            method=vae.encode)
    return vae.config.to_diffusion_latents(posterior.sample_from_noise(noise[None]))[0]

  return jax.lax.map(encode_one, (images, posterior_noise))


def _decode(models: DiffusionModels, latents: jax.Array) -> jax.Array:
  """Diffusion latents -> [B, H, W, 3] images in [0, 1] (diffusers' decode + postprocess)."""
  vae = models.vae

  def decode_one(one_latents):
    z = vae.config.from_diffusion_latents(one_latents[None])
    return vae.apply({"params": models.vae_params}, z, method=vae.decode)[0]

  return jnp.clip(jax.lax.map(decode_one, latents) * 0.5 + 0.5, 0.0, 1.0)


def _control_image(models: DiffusionModels, control: jax.Array) -> jax.Array:
  """The control image with the ControlNet's channel count (a grey image is repeated, as PIL's
  convert("RGB") of the control image does in diffusers)."""
  channels = models.controlnet.config.conditioning_channels
  if control.shape[-1] == 1 and channels != 1:
    control = jnp.repeat(control, channels, axis=-1)
  if control.shape[-1] != channels:
    raise InputError(f"control has {control.shape[-1]} channels but the ControlNet takes "
                     f"{channels}", field="control")
  return control


def _predict_noise(models: DiffusionModels, constants: _LoopConstants, settings: SamplerSettings,
                   guidance_scale: jax.Array, controlnet_conditioning_scale: jax.Array,
                   model_input: jax.Array, timestep: jax.Array) -> jax.Array:
  """The guided noise (or v) prediction for the scheduler-scaled latents [B, h, w, C]."""
  guided = settings.classifier_free_guidance
  twice = lambda x: jnp.concatenate([x, x]) if guided else x
  batch_latents = twice(model_input)
  residuals = None
  if models.controlnet is not None:
    controlnet = functools.partial(models.controlnet.apply, {"params": models.controlnet_params},
                                   guess_mode=settings.guess_mode)
    if settings.guess_mode and guided:
      # The ControlNet sees only the conditional half; the unconditional half gets nothing.
      conditional = lambda x: None if x is None else x[model_input.shape[0]:]
      residuals = controlnet(model_input, timestep, conditional(constants.text_states),
                             constants.control, controlnet_conditioning_scale,
                             text_embeds=conditional(constants.text_embeds),
                             time_ids=conditional(constants.time_ids))
      residuals = jax.tree.map(lambda r: jnp.concatenate([jnp.zeros_like(r), r]), residuals)
    else:
      residuals = controlnet(batch_latents, timestep, constants.text_states,
                             twice(constants.control), controlnet_conditioning_scale,
                             text_embeds=constants.text_embeds, time_ids=constants.time_ids)
  unet_input = batch_latents
  if models.inpainting_unet:
    unet_input = jnp.concatenate([batch_latents, twice(constants.mask),
                                  twice(constants.masked_image_latents)], axis=-1)
  prediction = models.unet.apply({"params": models.unet_params}, unet_input, timestep,
                                 constants.text_states, text_embeds=constants.text_embeds,
                                 time_ids=constants.time_ids, control=residuals)
  if not guided:
    return prediction
  unconditional, conditional = jnp.split(prediction, 2)
  return unconditional + guidance_scale * (conditional - unconditional)


def _text_conditioning(prompt: PromptEmbeddings, time_ids: jax.Array | None, batch: int,
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


@functools.partial(jax.jit, static_argnames=("settings",))
def sample(models: DiffusionModels, schedule: Schedule, prompt: PromptEmbeddings,
           time_ids: jax.Array | None, inputs: InpaintingInputs, noise: SamplerNoise,
           guidance: Guidance, settings: SamplerSettings) -> jax.Array:
  """Inpaints a batch: preprocessing, the denoising loop and decoding in one compiled program.

  Args:
    models: the networks and their parameters.
    schedule: `schedulers.make_schedule(config, num_inference_steps, strength)`; its step count
      S is the number of steps run.
    prompt: text conditioning with 1 or B rows (negative embeddings needed under guidance; SDXL
      also the pooled embeddings).
    time_ids: SDXL's [1 or B, 6] (original size, crop top-left, target size); None otherwise.
    inputs: images, masks and control images (see `InpaintingInputs`).
    noise: every random draw (`draw_noise`, or injected arrays for parity with a reference).
    guidance: the traced guidance scale and per-step ControlNet scales [S].
    settings: the static choices (see `SamplerSettings`).

  Returns:
    [B, H, W, 3] float32 images in [0, 1].
  """
  image, mask = inputs.image, inputs.mask
  batch, height, width = image.shape[:3]
  factor = models.latent_factor
  if height % factor or width % factor:
    raise InputError(f"image size {height}x{width} is not a multiple of the latent factor "
                     f"{factor}", field="image")
  if (models.controlnet is None) != (inputs.control is None):
    raise InputError("a control image is needed exactly when the pipeline has a ControlNet",
                     field="control")
  latent_height, latent_width = height // factor, width // factor
  binary_mask = binarize_mask(mask)
  pixels = 2.0 * image - 1.0

  # The image (strength < 1 or latent blending) and the masked image (inpainting UNet), in one
  # sequence of per-image encoder passes.
  needs_image_latents = settings.start_from_image or not models.inpainting_unet
  to_encode = []
  if needs_image_latents:
    to_encode.append((pixels, noise.image_posterior))
  if models.inpainting_unet:
    to_encode.append((pixels * (binary_mask < 0.5), noise.masked_image_posterior))
  encoded = jnp.split(_encode(models, jnp.concatenate([images for images, _ in to_encode]),
                              jnp.concatenate([draws for _, draws in to_encode])),
                      len(to_encode))
  image_latents = encoded[0] if needs_image_latents else None
  text_states, text_embeds, batch_time_ids = _text_conditioning(
      prompt, time_ids, batch, settings.classifier_free_guidance)
  constants = _LoopConstants(
      text_states=text_states, text_embeds=text_embeds, time_ids=batch_time_ids,
      control=None if inputs.control is None else _control_image(models, inputs.control),
      mask=downsample_mask(binary_mask, latent_height, latent_width),
      masked_image_latents=encoded[-1] if models.inpainting_unet else None,
      image_latents=image_latents, initial_noise=noise.latents)

  if settings.start_from_image:
    latents = schedule.add_noise(image_latents, noise.latents, 0)
  else:
    latents = noise.latents * schedule.init_noise_sigma
  last_step = schedule.num_steps - 1

  def denoise(carry, step):
    latents, solver_state = carry
    step_index, step_noise = step
    prediction = _predict_noise(models, constants, settings, guidance.guidance_scale,
                                guidance.controlnet_conditioning_scale[step_index],
                                schedule.scale_model_input(latents, step_index),
                                schedule.timesteps[step_index])
    latents, solver_state = schedule.step(solver_state, step_index, prediction, latents,
                                          noise=step_noise)
    if not models.inpainting_unet:
      # Outside the mask: the original, at the noise level the next step starts from.
      renoised = schedule.add_noise(constants.image_latents, constants.initial_noise,
                                    jnp.minimum(step_index + 1, last_step))
      original = jnp.where(step_index < last_step, renoised, constants.image_latents)
      latents = (1.0 - constants.mask) * original + constants.mask * latents
    return (latents, solver_state), None

  steps = (jnp.arange(schedule.num_steps), jnp.swapaxes(noise.steps, 0, 1))
  (latents, _), _ = jax.lax.scan(denoise, (latents, schedule.init_solver_state(latents)), steps)
  generated = _decode(models, latents)
  if settings.paste_back:
    generated = paste_back(image, generated, blur_mask(mask, settings.mask_blur))
  return generated
