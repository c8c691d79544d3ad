"""The compiled ControlNet inpainting sampler: diffusers' inpainting loop as one XLA program.

`sample` runs what diffusers' `StableDiffusionControlNetInpaintPipeline` and
`StableDiffusionXLControlNetInpaintPipeline` do between preprocessing the inputs and
post-processing the output, in one `jit`: mask binarisation and downsampling, VAE encoding of the
image and the masked image, the control image's embedding, the initial latents (img2img strength
included), the denoising loop under `lax.scan`, VAE decoding and an optional paste-back. The loop
carries only the latents and the solver state, so no per-step activation outlives its step.

What each step computes (B samples; "2B" under classifier-free guidance, unconditional half first):
  * UNet input: the scheduler-scaled latents, and for a 9-channel inpainting UNet the
    downsampled mask and the masked image's latents concatenated after them (channels 4 + 1 + 4);
  * ControlNet residuals at scale `controlnet_conditioning_scale * keep[step]` (diffusers'
    `controlnet_keep` from control_guidance_start/end); in guess mode under guidance the
    ControlNet sees only the conditional half and the unconditional half gets zero residuals, as
    diffusers does;
  * guidance: eps_uncond + guidance_scale * (eps_cond - eps_uncond) (`guidance`);
  * the scheduler step (`solvers`); for a 4-channel UNet, latent blending: outside the mask the
    latents are replaced by the original image's latents re-noised to the next step's level
    (diffusers' `init_latents_proper`), after the last step by the clean latents.

Static (part of the compiled program): the models' architectures, input shapes and batch size,
the number of steps run, the scheduler kind and `SamplerSettings` (guidance on/off, guess mode,
start from the image or from noise, paste-back and its blur radius). Traced (new values reuse the
compiled program): all parameters, prompt embeddings, SDXL time ids, images, masks, control
images, noise, `guidance_scale`, the per-step ControlNet scales and the schedule's arrays.

Batching: every per-sample input (images, masks, control images, noise) leads with the batch
axis B (prompt embeddings and time ids: B rows or one shared row), and sample b depends only on
row b of each: a batch of views is one call, `jax.vmap` over a further leading axis (in_axes 0
for the per-sample inputs, None for the rest) equals flattening it into B, and `shard_map` can
split B across devices. Noise drawn by `draw_noise` from per-sample keys keeps the property.

Numerical conventions that match diffusers exactly (the mask's are `mask_processing`'s):
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
from flax import struct

from signerf_jax.clip.text import PromptEmbeddings
from signerf_jax.diffusion import guidance as guidance_lib
from signerf_jax.diffusion import layers
from signerf_jax.diffusion import mask_processing
from signerf_jax.diffusion import vae as vae_lib
from signerf_jax.diffusion.controlnet import ControlNet
from signerf_jax.diffusion.solvers import Schedule
from signerf_jax.diffusion.unet import UNet2DCondition
from signerf_jax.diffusion.vae import AutoencoderKL
from signerf_jax.errors import InputError


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
    control_embedding: [B, h, w, E] `guidance.embed_control` of `control` if computed already.
  """
  image: jax.Array
  mask: jax.Array
  control: jax.Array | None = None
  control_embedding: jax.Array | None = None


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
    winograd_convolutions: let large 3x3 convolutions on a CPU run by Winograd's algorithm
      (faster, slower to compile: `layers.winograd_convolutions`); results agree to rounding.
  """
  classifier_free_guidance: bool = True
  guess_mode: bool = False
  start_from_image: bool = False
  paste_back: bool = False
  mask_blur: float = 0.0
  winograd_convolutions: bool = True


@functools.partial(jax.jit, static_argnames=("latent_shape", "num_steps"))
def draw_noise(keys: jax.Array, latent_shape: tuple[int, int, int], num_steps: int) -> SamplerNoise:
  """Standard-normal `SamplerNoise` from one PRNG key per sample.

  Args:
    keys: [B] PRNG keys; sample b's noise depends only on keys[b].
    latent_shape: (h, w, C).
    num_steps: S, the steps run.
  """
  def one_sample(key):
    latents_key, image_key, masked_image_key, steps_key = jax.random.split(key, 4)
    # Drawn flat and reshaped: the same values (partitionable threefry counts elements in
    # row-major order), but XLA compiles a flat draw ~3x faster than a 3-D or 4-D one, whose
    # compilation was most of a cold preview's outside the sampler.
    normal = lambda k, shape: jax.random.normal(k, (math.prod(shape),), jnp.float32).reshape(
        shape)
    return SamplerNoise(latents=normal(latents_key, latent_shape),
                        image_posterior=normal(image_key, latent_shape),
                        masked_image_posterior=normal(masked_image_key, latent_shape),
                        steps=normal(steps_key, (num_steps, *latent_shape)))
  return jax.vmap(one_sample)(keys)


# ----------------------------------------------------------------------------------------------
# The sampler.


@struct.dataclass
class _LoopConstants:
  """What every step reads (no step writes it). Text fields are 2B long under guidance."""
  text_states: jax.Array
  text_embeds: jax.Array | None
  time_ids: jax.Array | None
  control_embedding: jax.Array | None  # [B, h, w, E], the control images' embedding.
  mask: jax.Array  # [B, h, w, 1] binary.
  masked_image_latents: jax.Array | None  # Inpainting UNets.
  image_latents: jax.Array | None  # Starting from the image, and latent blending.
  initial_noise: jax.Array


def _check_inputs(models: DiffusionModels, inputs: InpaintingInputs) -> None:
  """Raises InputError unless the image size fits the VAE and a ControlNet gets control images."""
  height, width = inputs.image.shape[1:3]
  factor = models.latent_factor
  if height % factor or width % factor:
    raise InputError(f"image size {height}x{width} is not a multiple of the latent factor "
                     f"{factor}", field="image")
  if (models.controlnet is None) != (inputs.control is None):
    raise InputError("a control image is needed exactly when the pipeline has a ControlNet",
                     field="control")


def _encode_inputs(models: DiffusionModels, image: jax.Array, binary_mask: jax.Array,
                   noise: SamplerNoise, settings: SamplerSettings
                   ) -> tuple[jax.Array | None, jax.Array | None]:
  """(the image's latents, the masked image's latents), in one sequence of per-image encoder
  passes: the first when starting from the image (strength < 1) or blending latents, the
  second for an inpainting UNet, else None."""
  pixels = 2.0 * image - 1.0
  needs_image_latents = settings.start_from_image or not models.inpainting_unet
  to_encode = []
  if needs_image_latents:
    to_encode.append((pixels, noise.image_posterior))
  if models.inpainting_unet:
    to_encode.append((pixels * (binary_mask < 0.5), noise.masked_image_posterior))
  encoded = jnp.split(
      vae_lib.encode_to_latents(models.vae, models.vae_params,
                                jnp.concatenate([images for images, _ in to_encode]),
                                jnp.concatenate([draws for _, draws in to_encode])),
      len(to_encode))
  return (encoded[0] if needs_image_latents else None,
          encoded[-1] if models.inpainting_unet else None)


def _loop_constants(models: DiffusionModels, prompt: PromptEmbeddings,
                    time_ids: jax.Array | None, inputs: InpaintingInputs, noise: SamplerNoise,
                    settings: SamplerSettings) -> _LoopConstants:
  """What the steps read: the encoded images, the mask at latent resolution, the text rows of
  the UNet batch and the control images' embedding."""
  batch, height, width = inputs.image.shape[:3]
  factor = models.latent_factor
  binary_mask = mask_processing.binarize_mask(inputs.mask)
  image_latents, masked_image_latents = _encode_inputs(models, inputs.image, binary_mask, noise,
                                                       settings)
  text_states, text_embeds, batch_time_ids = guidance_lib.text_conditioning(
      prompt, time_ids, batch, settings.classifier_free_guidance)
  control_embedding = inputs.control_embedding
  if inputs.control is not None and control_embedding is None:
    control_embedding = guidance_lib.embed_control(models.controlnet, models.controlnet_params,
                                                   inputs.control)
  return _LoopConstants(
      text_states=text_states, text_embeds=text_embeds, time_ids=batch_time_ids,
      control_embedding=control_embedding,
      mask=mask_processing.downsample_mask(binary_mask, height // factor, width // factor),
      masked_image_latents=masked_image_latents, image_latents=image_latents,
      initial_noise=noise.latents)


def _predict_noise(models: DiffusionModels, constants: _LoopConstants, settings: SamplerSettings,
                   guidance: guidance_lib.Guidance, step_index: jax.Array,
                   model_input: jax.Array, timestep: jax.Array) -> jax.Array:
  """The guided noise (or v) prediction for the scheduler-scaled latents [B, h, w, C] at step
  `step_index` of the run (which selects its ControlNet conditioning scale)."""
  guided = settings.classifier_free_guidance
  batch_latents = guidance_lib.both_halves(model_input, guided)
  residuals = None
  if models.controlnet is not None:
    controlnet = functools.partial(
        models.controlnet.apply, {"params": models.controlnet_params}, controlnet_cond=None,
        controlnet_conditioning_scale=guidance.controlnet_conditioning_scale[step_index],
        guess_mode=settings.guess_mode)
    if settings.guess_mode and guided:
      # The ControlNet sees only the conditional half; the unconditional half gets nothing.
      conditional = lambda x: None if x is None else x[model_input.shape[0]:]
      residuals = controlnet(model_input, timestep, conditional(constants.text_states),
                             text_embeds=conditional(constants.text_embeds),
                             time_ids=conditional(constants.time_ids),
                             conditioning_embedding=constants.control_embedding)
      residuals = jax.tree.map(lambda r: jnp.concatenate([jnp.zeros_like(r), r]), residuals)
    else:
      residuals = controlnet(batch_latents, timestep, constants.text_states,
                             text_embeds=constants.text_embeds, time_ids=constants.time_ids,
                             conditioning_embedding=guidance_lib.both_halves(
                                 constants.control_embedding, guided))
  unet_input = batch_latents
  if models.inpainting_unet:
    unet_input = jnp.concatenate(
        [batch_latents, guidance_lib.both_halves(constants.mask, guided),
         guidance_lib.both_halves(constants.masked_image_latents, guided)], axis=-1)
  prediction = models.unet.apply({"params": models.unet_params}, unet_input, timestep,
                                 constants.text_states, text_embeds=constants.text_embeds,
                                 time_ids=constants.time_ids, control=residuals)
  if not guided:
    return prediction
  return guidance_lib.classifier_free_guidance(prediction, guidance.guidance_scale)


def _denoise(models: DiffusionModels, schedule: Schedule, constants: _LoopConstants,
             guidance: guidance_lib.Guidance, settings: SamplerSettings, latents: jax.Array,
             step_noise: jax.Array) -> jax.Array:
  """The denoising loop under `lax.scan`, carrying only the latents [B, h, w, C] and the solver
  state: the latents at the first step's noise level -> the clean latents.

  Args:
    step_noise: [B, S, h, w, C], each step's fresh noise (ancestral schedules).
  """
  last_step = schedule.num_steps - 1

  def denoise(carry, step):
    latents, solver_state = carry
    step_index, step_noise = step
    prediction = _predict_noise(models, constants, settings, guidance, step_index,
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

  steps = (jnp.arange(schedule.num_steps), jnp.swapaxes(step_noise, 0, 1))
  (latents, _), _ = jax.lax.scan(denoise, (latents, schedule.init_solver_state(latents)), steps)
  return latents


@functools.partial(jax.jit, static_argnames=("settings",))
def sample(models: DiffusionModels, schedule: Schedule, prompt: PromptEmbeddings,
           time_ids: jax.Array | None, inputs: InpaintingInputs, noise: SamplerNoise,
           guidance: guidance_lib.Guidance, settings: SamplerSettings) -> jax.Array:
  """Inpaints a batch: preprocessing, the denoising loop and decoding in one compiled program.

  Args:
    models: the networks and their parameters.
    schedule: `solvers.make_schedule(config, num_inference_steps, strength)`; its step count S
      is the number of steps run.
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
  _check_inputs(models, inputs)
  with layers.winograd_convolutions(settings.winograd_convolutions):
    constants = _loop_constants(models, prompt, time_ids, inputs, noise, settings)
    if settings.start_from_image:
      latents = schedule.add_noise(constants.image_latents, noise.latents, 0)
    else:
      latents = noise.latents * schedule.init_noise_sigma
    latents = _denoise(models, schedule, constants, guidance, settings, latents, noise.steps)
    # diffusers' postprocess: [-1, 1] -> [0, 1].
    decoded = vae_lib.decode_from_latents(models.vae, models.vae_params, latents)
  generated = jnp.clip(decoded * 0.5 + 0.5, 0.0, 1.0)
  if settings.paste_back:
    generated = mask_processing.paste_back(
        inputs.image, generated, mask_processing.blur_mask(inputs.mask, settings.mask_blur))
  return generated


# How XLA:CPU compiles the sampler for float32 models. jaxlib 0.10's XLA:CPU hands every matmul
# to YNNPACK by default (a "__ynn_fusion" per dot in the optimised HLO); this option keeps them
# XLA's own dots, which measured faster for the shipped model's sampler on CPUs
# (docs/performance.md); SD 1.5's UNet changes within noise and NeRF training is slower, so only
# this program sets it. bfloat16 models keep XLA's defaults: without YNNPACK SD 1.5's bfloat16
# UNet ran slower (the shipped model's faster), and those measurements were on a CPU without
# bfloat16 instructions, while bfloat16 pays only on CPUs with them. On GPUs and TPUs, where the
# option means nothing, the sampler keeps XLA's defaults too.
CPU_FLOAT32_COMPILER_OPTIONS = {"xla_cpu_experimental_ynn_fusion_type": ""}
_CPU_FLOAT32_SAMPLE = jax.jit(sample.__wrapped__, static_argnames=("settings",),
                              compiler_options=CPU_FLOAT32_COMPILER_OPTIONS)


def program(models: DiffusionModels, backend: str | None = None):
  """The jitted sampler `pipeline.generate` runs for `models` (`sample`'s arguments, `settings`
  by keyword): `sample` compiled with `CPU_FLOAT32_COMPILER_OPTIONS` when the UNet computes in
  float32 on a CPU `backend` (None: JAX's default), `sample` itself otherwise. Like any jit
  with compiler options, the float32 one cannot be called inside another jit: there call
  `sample`, which that jit's options then compile."""
  float32 = jnp.dtype(models.unet.compute_dtype) == jnp.float32
  cpu = layers.backend_or_default(backend) == "cpu"
  return _CPU_FLOAT32_SAMPLE if float32 and cpu else sample
