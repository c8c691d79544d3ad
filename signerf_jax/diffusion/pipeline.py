"""A diffusers ControlNet inpainting pipeline: loading it, encoding prompts, generating.

Equivalent to diffusers' `StableDiffusionControlNetInpaintPipeline` (SD 1.x / 2.x) and
`StableDiffusionXLControlNetInpaintPipeline` (SDXL, chosen when the UNet has `text_time`
conditioning), with inputs as NHWC arrays in [0, 1] at the generation resolution:

    pipeline = load_pipeline("checkpoints/sd15-inpainting",
                             controlnet="checkpoints/controlnet-depth",
                             scheduler_kind="dpm_solver_multistep")
    prompt = encode_prompts(pipeline, ["a red armchair"])
    images = generate(pipeline, prompt, image, mask, control, key=jax.random.key(0),
                      options=GenerationOptions(num_inference_steps=20, strength=0.9))

To batch differently (e.g. `jax.vmap` over groups of views, or `shard_map` over devices), call
`sampler.program(pipeline.models)` (or `sampler.sample` inside your own jit) with the pieces
`sampler_setup` returns, as `generate` does.

`generate` equals the diffusers pipeline called with `output_type="np"`, numpy inputs of the
output size (no resizing), `num_images_per_prompt=1`, `eta=0`, no `padding_mask_crop`,
`clip_skip`, `guidance_rescale`, `denoising_start/end`, IP-adapters or multi-ControlNets, and
the same random draws (see `sampler.SamplerNoise` for the reference's order). The paste-back
(`GenerationOptions.paste_back`) is diffusers' `apply_overlay` without the crop (see
`mask_processing.paste_back`); diffusers applies it only together with `padding_mask_crop`.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from pathlib import Path
from typing import Annotated, Any, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from signerf_jax import safetensors_io, validation
from signerf_jax.clip import text as clip_text
from signerf_jax.clip.tokenizer import Tokenizer, load_tokenizer
from signerf_jax.diffusion import guidance as guidance_lib
from signerf_jax.diffusion import (controlnet as controlnet_lib, layers, model_configs,
                                   pipeline_components, sampler, schedulers, solvers)
from signerf_jax.diffusion.attention import AttentionOptions
from signerf_jax.diffusion.layers import Dtype
from signerf_jax.errors import InputError
from signerf_jax.validation import (NonNegativeFloat, NonNegativeInt, PositiveInt, Range,
                                    UnitInterval)



@dataclasses.dataclass(frozen=True, eq=False)
class Pipeline:
  """A loaded inpainting pipeline.

  Attributes:
    models: the UNet, VAE and optional ControlNet with their parameters.
    tokenizers, text_encoders: SD: (tokenizer,), (text_encoder,); SDXL: both pairs, or only
      the second for checkpoints without the first encoder.
    scheduler: the noise schedule configuration.
    force_zeros_for_empty_prompt: SDXL's unconditional embedding without negative prompt is
      zeros (model_index.json; True unless the checkpoint says otherwise).
  """
  models: sampler.DiffusionModels
  tokenizers: tuple[Tokenizer, ...]
  text_encoders: tuple[clip_text.TextEncoder, ...]
  scheduler: schedulers.SchedulerConfig
  force_zeros_for_empty_prompt: bool = True

  @property
  def is_sdxl(self) -> bool:
    return self.models.unet.config.addition_embed_type == "text_time"


def load_pipeline(path: str | os.PathLike | None = None, *,
                  unet: str | os.PathLike | None = None,
                  controlnet: str | os.PathLike | None = None,
                  vae: str | os.PathLike | None = None,
                  text_encoder: str | os.PathLike | None = None,
                  text_encoder_2: str | os.PathLike | None = None,
                  tokenizer: str | os.PathLike | None = None,
                  tokenizer_2: str | os.PathLike | None = None,
                  scheduler: str | os.PathLike | None = None,
                  scheduler_kind: str | None = None,
                  scheduler_options: Mapping[str, Any] | None = None,
                  dtype=np.float32, compute_dtype: Dtype = jnp.float32,
                  variant: str | None = None,
                  attention: AttentionOptions = AttentionOptions()) -> Pipeline:
  """Loads a diffusers pipeline directory and/or separately stored components.

  Args:
    path: a pipeline directory (`model_index.json` naming its component subfolders); None when
      every needed component is given explicitly.
    unet, controlnet, vae, text_encoder, text_encoder_2, tokenizer, tokenizer_2, scheduler:
      component directories replacing (or adding to) the pipeline's, e.g. a ControlNet stored
      apart from its base model. Needed: unet, vae, scheduler, and text_encoder + tokenizer
      (SD) or text_encoder_2 + tokenizer_2 (SDXL); the ControlNet is optional.
    scheduler_kind: "ddim", "dpm_solver_multistep" or "euler_ancestral", reusing the
      checkpoint's schedule (needed when its scheduler class is not one of these, e.g. PNDM).
    scheduler_options: scheduler fields to override (e.g. {"use_karras_sigmas": True}).
    dtype: storage dtype of the UNet, ControlNet and VAE parameters (float32 or bfloat16).
      bfloat16 storage saves memory in the sampler only with a bfloat16 `compute_dtype`: with
      float32 compute, XLA hoists the weights' conversion out of the denoising loop and holds
      float32 copies of them.
    compute_dtype: float32, or bfloat16 matmuls/convolutions with float32 accumulation.
    variant: diffusers weight variant ("fp16" reads *.fp16.safetensors).
    attention: how the UNet, ControlNet and VAE evaluate attention (speed and memory only).

  Raises:
    InputError naming a missing component and where it was looked for, or the file and field
    of anything malformed.
  """
  path = None if path is None else Path(path)
  components = pipeline_components.find_components(path, dict(
      unet=unet, controlnet=controlnet, vae=vae, text_encoder=text_encoder,
      text_encoder_2=text_encoder_2, tokenizer=tokenizer, tokenizer_2=tokenizer_2,
      scheduler=scheduler))
  if components.options.get("requires_aesthetics_score"):
    raise InputError("aesthetic-score conditioning (SDXL refiner) is not implemented",
                     path / pipeline_components.MODEL_INDEX, "requires_aesthetics_score")
  models = pipeline_components.load_networks(components, dtype, variant=variant,
                                             attention=attention, compute_dtype=compute_dtype)
  tokenizers, text_encoders = pipeline_components.load_text_encoders(
      components, models.unet.config.addition_embed_type == "text_time")
  scheduler_config = schedulers.load_scheduler_config(
      components.require("scheduler"), scheduler_kind, **(scheduler_options or {}))
  return Pipeline(models, tokenizers, text_encoders, scheduler_config,
                  bool(components.options.get("force_zeros_for_empty_prompt", True)))


def check_pipeline(path: str | os.PathLike, *, controlnet: str | os.PathLike | None = None,
                   scheduler_kind: str | None = None) -> tuple[Tokenizer, ...]:
  """Checks what `load_pipeline(path, controlnet=..., scheduler_kind=...)` needs without reading
  any weights (a second, not the minutes a large checkpoint takes to load): every needed
  component is found, and the UNet, VAE, ControlNet and scheduler configurations and the
  tokenizers parse.

  Returns:
    the pipeline's tokenizers (small; e.g. to check a prompt's words).
  Raises:
    InputError as `load_pipeline` would, naming the file and field.
  """
  components = pipeline_components.find_components(Path(path), {"controlnet": controlnet})
  parsers = {"unet": model_configs.UNetConfig, "vae": model_configs.AutoencoderConfig,
             "controlnet": model_configs.ControlNetConfig}
  configs = {}
  for name, parser in parsers.items():
    if name == "controlnet" and name not in components.directories:
      continue
    directory = model_configs.component_directory(components.require(name), name)
    configs[name] = parser.from_dict(model_configs.read_config(directory),
                                     directory / "config.json")
    safetensors_io.find_weight_files(directory)  # Found, and a shard index's entries inside it.
  sdxl = configs["unet"].addition_embed_type == "text_time"
  tokenizers = tuple(load_tokenizer(components.require(name))
                     for name in (("tokenizer_2",) if sdxl else ("tokenizer",)))
  schedulers.load_scheduler_config(components.require("scheduler"), scheduler_kind)
  return tokenizers


def encode_prompts(pipeline: Pipeline, prompts: str | Sequence[str],
                   negative_prompts: str | Sequence[str] | None = None, *,
                   prompts_2: str | Sequence[str] | None = None,
                   negative_prompts_2: str | Sequence[str] | None = None,
                   guidance: bool = True) -> clip_text.PromptEmbeddings:
  """The pipeline's text conditioning, as its diffusers pipeline's `encode_prompt`.

  Args:
    prompts: one prompt per sample, or one for all (the sampler broadcasts a single row).
    negative_prompts: the unconditional prompts (None: "" for SD, zeros for SDXL with
      force_zeros_for_empty_prompt).
    prompts_2, negative_prompts_2: SDXL's prompts for the second encoder (default: the same).
    guidance: also encode the unconditional branch (needed when guidance_scale > 1).
  """
  if pipeline.is_sdxl:
    return clip_text.encode_prompt_sdxl(
        pipeline.tokenizers, pipeline.text_encoders, prompts, prompts_2, negative_prompts,
        negative_prompts_2, guidance, pipeline.force_zeros_for_empty_prompt)
  if prompts_2 is not None or negative_prompts_2 is not None:
    raise InputError("prompts_2 is SDXL's second prompt; this pipeline has one text encoder",
                     field="prompts_2")
  return clip_text.encode_prompt(pipeline.tokenizers[0], pipeline.text_encoders[0], prompts,
                                 negative_prompts, guidance)


@dataclasses.dataclass(frozen=True)
class GenerationOptions(validation.CheckedFields):
  """The knobs of a generation (diffusers' argument names and meanings; gin:
  `GenerationOptions.<field>`).

  Attributes:
    num_inference_steps: steps of the full schedule; int(steps * strength) of them run.
    strength: 1 starts from noise; below 1 from the image noised to that level (the paper's
      "denoising strength", 0.5 - 0.95).
    guidance_scale: classifier-free guidance weight; <= 1 disables guidance (half the work).
    controlnet_conditioning_scale: multiplies the ControlNet residuals (paper: 0.4 - 1.0).
    control_guidance_start, control_guidance_end: the fraction of the steps run in which the
      ControlNet acts.
    guess_mode: ControlNet guess mode.
    paste_back: composite the output over the input image through the mask.
    mask_blur: Gaussian blur radius (pixels, PIL's `GaussianBlur`) of the paste-back mask.
    original_size, crops_coords_top_left, target_size: SDXL's size conditioning in pixels
      (height, width) / (top, left); None sizes default to the image size.
  """
  num_inference_steps: PositiveInt = 20
  strength: Annotated[float, Range(0, 1, low_inclusive=False)] = 1.0
  guidance_scale: NonNegativeFloat = 7.5
  controlnet_conditioning_scale: NonNegativeFloat = 1.0
  control_guidance_start: UnitInterval = 0.0
  control_guidance_end: UnitInterval = 1.0
  guess_mode: bool = False
  paste_back: bool = False
  mask_blur: NonNegativeFloat = 0.0
  original_size: tuple[PositiveInt, PositiveInt] | None = None
  crops_coords_top_left: tuple[NonNegativeInt, NonNegativeInt] = (0, 0)
  target_size: tuple[PositiveInt, PositiveInt] | None = None

  def __post_init__(self):
    super().__post_init__()
    if int(self.num_inference_steps * self.strength) < 1:
      raise InputError(f"strength {self.strength} of {self.num_inference_steps} steps leaves "
                       "no step to run", field="GenerationOptions.strength")
    if self.control_guidance_start >= self.control_guidance_end:
      raise InputError(f"must be below control_guidance_end {self.control_guidance_end}, got "
                       f"{self.control_guidance_start}",
                       field="GenerationOptions.control_guidance_start")


def sdxl_time_ids(height: int, width: int, options: GenerationOptions) -> np.ndarray:
  """[1, 6] float32 add_time_ids: original size, crop top-left, target size (pixels)."""
  original = options.original_size or (height, width)
  target = options.target_size or (height, width)
  return np.asarray([[*original, *options.crops_coords_top_left, *target]], np.float32)


@dataclasses.dataclass(frozen=True)
class SamplerSetup:
  """Everything `sampler.sample` takes besides the models, prompt, inputs and noise.

  Attributes:
    schedule: the steps run (`solvers.make_schedule` with the options' strength).
    time_ids: SDXL's [1, 6] size conditioning; None for SD.
    guidance: the traced guidance scale and per-step ControlNet scales.
    settings: the static choices.
  """
  schedule: solvers.Schedule
  time_ids: jax.Array | None
  guidance: guidance_lib.Guidance
  settings: sampler.SamplerSettings


def sampler_setup(pipeline: Pipeline, height: int, width: int,
                  options: GenerationOptions = GenerationOptions(),
                  winograd_convolutions: bool = True) -> SamplerSetup:
  """The sampler's schedule, conditioning and settings for images of height x width pixels
  (`winograd_convolutions`: see `sampler.SamplerSettings`).

  `generate` calls `sampler.program(pipeline.models)` with these; call it directly to vmap or
  shard it.
  """
  models = pipeline.models
  schedule = solvers.make_schedule(pipeline.scheduler, options.num_inference_steps,
                                   options.strength)
  guess_mode = options.guess_mode
  if models.controlnet is not None and not pipeline.is_sdxl:
    # The SD pipeline (not the SDXL one) forces guess mode for pooled-condition ControlNets.
    guess_mode = guess_mode or models.controlnet.config.global_pool_conditions
  settings = sampler.SamplerSettings(
      classifier_free_guidance=options.guidance_scale > 1.0, guess_mode=guess_mode,
      start_from_image=options.strength < 1.0, paste_back=options.paste_back,
      mask_blur=float(options.mask_blur) if options.paste_back else 0.0,
      winograd_convolutions=winograd_convolutions)
  guidance = guidance_lib.Guidance(
      guidance_scale=jnp.float32(options.guidance_scale),
      controlnet_conditioning_scale=jnp.asarray(
          guidance_lib.controlnet_conditioning_scale_per_step(
              schedule.num_steps, options.controlnet_conditioning_scale,
              options.control_guidance_start, options.control_guidance_end)))
  time_ids = jnp.asarray(sdxl_time_ids(height, width, options)) if pipeline.is_sdxl else None
  return SamplerSetup(schedule, time_ids, guidance, settings)


def _batch_of_keys(key: jax.Array, batch: int) -> jax.Array:
  """[B] typed keys: one key is split into B, a batch of B keys is taken as is."""
  if not jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key):
    key = jax.random.wrap_key_data(key)  # Raw uint32 key data (jax.random.PRNGKey).
  keys = jax.random.split(key, batch) if key.ndim == 0 else key
  if keys.shape != (batch,):
    raise InputError(f"expected one key or {batch} keys, got keys of shape {keys.shape}",
                     field="key")
  return keys


def _as_images(array, name: str, channels: int | None = None) -> jax.Array:
  """`array` as float32 [B, H, W, channels] (any channel count for None)."""
  array = jnp.asarray(array, jnp.float32)
  if array.ndim != 4 or channels not in (None, array.shape[-1]):
    raise InputError(f"expected [B, H, W, {channels or 'C'}] in [0, 1], got shape "
                     f"{array.shape}", field=name)
  return array


@functools.partial(jax.jit, static_argnames=("region", "winograd_convolutions"))
def control_embedding(models: sampler.DiffusionModels, control, base=None,
                      region: tuple[int, int, int, int] | None = None,
                      winograd_convolutions: bool = True) -> jax.Array:
  """The ControlNet's embedding of control images (`guidance.embed_control`), which `generate`
  takes as `control_embedding` instead of computing it.

  Args:
    models: the pipeline's networks (with a ControlNet).
    control: [B, H, W, C] in [0, 1], as `generate` takes it.
    base: None, or [1 or B, h, w, E] the embedding of control images that equal `control`
      outside the pixel rectangle `region` (top, left, height, width): then only the cells the
      rectangle reaches are computed (`controlnet.embed_conditioning_region`).
    winograd_convolutions: as `generate`'s, so that the convolutions round as its would.
  Returns:
    [B, H / f, W / f, E] (f the latent factor).
  """
  control = guidance_lib.control_image(jnp.asarray(control, jnp.float32),
                                       models.controlnet.config.conditioning_channels)
  with layers.winograd_convolutions(winograd_convolutions):
    if base is None:
      return controlnet_lib.embed_conditioning(models.controlnet, models.controlnet_params, control)
    return controlnet_lib.embed_conditioning_region(models.controlnet, models.controlnet_params,
                                                    base, control, region)


def generate(pipeline: Pipeline, prompt: clip_text.PromptEmbeddings, image, mask,
             control=None, *, key: jax.Array | None = None,
             noise: sampler.SamplerNoise | None = None,
             options: GenerationOptions = GenerationOptions(),
             winograd_convolutions: bool = True, control_embedding=None) -> jax.Array:
  """Inpaints B images in one compiled run.

  Args:
    pipeline: from `load_pipeline`.
    prompt: from `encode_prompts` (1 or B rows; with negatives when guidance_scale > 1).
    image: [B, H, W, 3] in [0, 1]; H and W multiples of the VAE's latent factor (8).
    mask: [B, H, W, 1] in [0, 1]; >= 0.5 is regenerated.
    control: [B, H, W, C] in [0, 1] for the ControlNet (C its conditioning channels, or 1);
      None for a pipeline without ControlNet.
    key: a PRNG key (split into one per sample) or [B] keys (sample b uses keys[b]).
    noise: instead of `key`, every random draw as arrays (see `sampler.SamplerNoise`).
    options: the generation knobs.
    winograd_convolutions: False compiles faster and samples slower
      (`sampler.SamplerSettings`; docs/performance.md): for a program that runs a few times.
    control_embedding: [B, H / f, W / f, E], the module's `control_embedding` of `control` when
      computed already (e.g. for images whose control differs only in a region), else None.

  Returns:
    [B, H, W, 3] float32 images in [0, 1].
  """
  image = _as_images(image, "image", 3)
  mask = _as_images(mask, "mask", 1)
  if control is not None:
    control = _as_images(control, "control")  # The sampler checks the channels.
  batch, height, width = image.shape[:3]
  for name, array in (("mask", mask), ("control", control)):
    if array is not None and tuple(array.shape[:3]) != (batch, height, width):
      raise InputError(f"expected batch and size {(batch, height, width)} like the image, got "
                       f"{tuple(array.shape[:3])}", field=name)
  setup = sampler_setup(pipeline, height, width, options, winograd_convolutions)
  if noise is None:
    if key is None:
      raise InputError("pass a PRNG key (or the noise arrays)", field="key")
    factor = pipeline.models.latent_factor
    noise = sampler.draw_noise(
        _batch_of_keys(key, batch),
        (height // factor, width // factor, pipeline.models.latent_channels),
        setup.schedule.num_steps)
  return sampler.program(pipeline.models)(
      pipeline.models, setup.schedule, prompt, setup.time_ids,
      sampler.InpaintingInputs(image, mask, control, control_embedding), noise, setup.guidance,
      settings=setup.settings)
