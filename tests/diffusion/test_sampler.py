"""The compiled sampler: noise, sheet-sized runs.

The full pipeline's parity with diffusers is in test_pipeline_parity.py.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from signerf_jax.clip import text as clip_text
from signerf_jax.diffusion import guidance as guidance_lib
from signerf_jax.diffusion import layers, model_configs, sampler, schedulers, solvers, weights
from signerf_jax.diffusion.controlnet import ControlNet
from signerf_jax.diffusion.unet import UNet2DCondition
from signerf_jax.diffusion.vae import AutoencoderKL
from signerf_jax.errors import InputError

TEXT_WIDTH = 16
# Small networks of the default model's shape: a VAE of latent factor 4 with mid-block
# attention over the whole latent, a 9-channel UNet and a matching ControlNet.
BACKBONE = dict(block_out_channels=[16, 32], norm_num_groups=8, layers_per_block=1,
                attention_head_dim=2, cross_attention_dim=TEXT_WIDTH,
                down_block_types=["CrossAttnDownBlock2D", "DownBlock2D"])
UNET = dict(BACKBONE, in_channels=9, up_block_types=["UpBlock2D", "CrossAttnUpBlock2D"])
CONTROLNET = dict(BACKBONE, conditioning_embedding_out_channels=[8, 8, 16])
VAE = dict(block_out_channels=[8, 16, 16], down_block_types=["DownEncoderBlock2D"] * 3,
           up_block_types=["UpDecoderBlock2D"] * 3, norm_num_groups=8, scaling_factor=0.5)


def tiny_models(unet_options=UNET) -> sampler.DiffusionModels:
  unet = UNet2DCondition(model_configs.UNetConfig.from_dict(unet_options))
  controlnet = ControlNet(model_configs.ControlNetConfig.from_dict(CONTROLNET))
  vae = AutoencoderKL(model_configs.AutoencoderConfig.from_dict(VAE))
  return sampler.DiffusionModels(weights.random_params(unet, 1), weights.random_params(vae, 2),
                                 weights.random_params(controlnet, 3), unet, vae, controlnet)


def test_models_must_fit_an_inpainting_pipeline():
  with pytest.raises(InputError, match="needs 4 .* or 9") as error:
    tiny_models(dict(UNET, in_channels=5))
  assert error.value.field == "unet.in_channels"


@pytest.mark.slow
def test_a_two_by_three_sheet_runs_and_memory_does_not_grow_with_the_steps():
  """A 256 x 384 sheet (64 x 96 latents: 6,144 tokens in every self-attention) of 2 x 3 tiles
  with only the bottom-right slot inpainted. The loop carries only latents and solver state, so
  the compiled program's working memory is the same for 2 and 5 steps."""
  models = tiny_models()
  height, width, tile = 256, 384, 128
  rng = np.random.default_rng(0)
  mask = np.zeros((1, height, width, 1), np.float32)
  mask[:, tile + 16:-16, 2 * tile + 16:-16] = 1.0  # Inside the slot.
  inputs = sampler.InpaintingInputs(image=jnp.asarray(rng.random((1, height, width, 3)),
                                                      jnp.float32),
                                    mask=jnp.asarray(mask),
                                    control=jnp.asarray(rng.random((1, height, width, 1)),
                                                        jnp.float32))
  prompt = clip_text.PromptEmbeddings(jnp.ones((1, 8, TEXT_WIDTH)), jnp.zeros((1, 8, TEXT_WIDTH)))
  config = schedulers.SchedulerConfig(kind="dpm_solver_multistep")
  settings = sampler.SamplerSettings(paste_back=True, mask_blur=0.0)

  def arguments(num_steps):
    schedule = solvers.make_schedule(config, num_steps)
    noise = sampler.draw_noise(jax.random.split(jax.random.key(0), 1),
                               (height // 4, width // 4, 4), num_steps)
    guidance = guidance_lib.Guidance(
        jnp.float32(7.5),
        jnp.asarray(guidance_lib.controlnet_conditioning_scale_per_step(num_steps, 0.8)))
    return models, schedule, prompt, None, inputs, noise, guidance

  compiled = {steps: sampler.program(models).lower(*arguments(steps), settings=settings).compile()
              for steps in (2, 5)}
  working_memory = {steps: program.memory_analysis().temp_size_in_bytes
                    for steps, program in compiled.items()}
  assert working_memory[2] == working_memory[5]
  assert working_memory[2] < 2**30

  out = np.asarray(compiled[2](*arguments(2)))
  assert out.shape == (1, height, width, 3) and np.isfinite(out).all()
  outside = mask[..., 0] == 0
  np.testing.assert_array_equal(out[outside], np.asarray(inputs.image)[outside])
  assert np.abs(out - np.asarray(inputs.image))[~outside].mean() > 0.05


def small_sheet_arguments(height: int, width: int) -> tuple:
  """`sampler.sample`'s arguments but the settings: the tiny models, 2 steps, one sheet."""
  rng = np.random.default_rng(1)
  image, mask, control = (jnp.asarray(rng.random((1, height, width, channels)), jnp.float32)
                          for channels in (3, 1, 1))
  schedule = solvers.make_schedule(schedulers.SchedulerConfig(kind="dpm_solver_multistep"), 2)
  return (tiny_models(), schedule,
          clip_text.PromptEmbeddings(jnp.ones((1, 8, TEXT_WIDTH)), jnp.zeros((1, 8, TEXT_WIDTH))),
          None, sampler.InpaintingInputs(image, jnp.round(mask), control),
          sampler.draw_noise(jax.random.split(jax.random.key(0), 1),
                             (height // 4, width // 4, 4), 2),
          guidance_lib.Guidance(jnp.float32(7.5), jnp.ones((2,), jnp.float32)))


@pytest.mark.slow
def test_winograd_convolutions_are_a_static_choice_with_equal_results(monkeypatch):
  """Without Winograd (the preview's quick-to-compile program) the sampler is its own compiled
  program, with XLA's convolutions where Winograd's matmuls were, and samples the same image to
  float rounding. The tiny networks take Winograd only with its size limits lowered."""
  monkeypatch.setattr(layers, "CPU_IM2COL_MAX_POSITIONS", 0)
  monkeypatch.setattr(layers, "CPU_WINOGRAD_MIN_TILES", 1)
  monkeypatch.setattr(layers, "CPU_WINOGRAD_MIN_CHANNELS", 8)
  # A size no other test samples, so no program is shared with them.
  arguments = small_sheet_arguments(40, 24)
  lowered = {winograd: sampler.program(arguments[0]).lower(
      *arguments, settings=sampler.SamplerSettings(winograd_convolutions=winograd))
             for winograd in (True, False)}
  convolutions = {winograd: program.as_text().count("stablehlo.convolution")
                  for winograd, program in lowered.items()}
  assert convolutions[False] > convolutions[True]
  images = {winograd: np.asarray(program.compile()(*arguments))
            for winograd, program in lowered.items()}
  np.testing.assert_allclose(images[False], images[True], atol=1e-4)
  image = arguments[4].image
  assert np.abs(images[True] - np.asarray(image)).mean() > 0.01  # It did generate something.


@pytest.mark.slow
def test_float32_models_sample_without_ynnpack_bfloat16_ones_with_xla_defaults():
  """`sampler.CPU_FLOAT32_COMPILER_OPTIONS` reach the float32 models' program: XLA:CPU's defaults
  (bfloat16 models' program, `sample` itself, and so a caller's own jit around it) hand its
  matmuls to YNNPACK fusions. Both compilations of the float32 models sample the same images to
  float rounding."""
  arguments = small_sheet_arguments(24, 32)
  models = arguments[0]
  bfloat16_models = models.replace(**{
      name: dataclasses.replace(getattr(models, name), compute_dtype=jnp.bfloat16)
      for name in ("unet", "controlnet")})
  settings = sampler.SamplerSettings()
  programs = {
      "float32": sampler.program(models).lower(*arguments, settings=settings),
      "bfloat16": sampler.program(bfloat16_models).lower(bfloat16_models, *arguments[1:],
                                                         settings=settings),
      "caller_jit": jax.jit(sampler.sample, static_argnames=("settings",)).lower(
          *arguments, settings=settings)}
  programs = {name: lowered.compile() for name, lowered in programs.items()}
  ynnpack_fusions = {name: program.as_text().count('"kind":"__ynn_fusion"')
                     for name, program in programs.items()}
  assert ynnpack_fusions["float32"] == 0
  assert ynnpack_fusions["bfloat16"] > 0 and ynnpack_fusions["caller_jit"] > 0
  np.testing.assert_allclose(np.asarray(programs["float32"](*arguments)),
                             np.asarray(programs["caller_jit"](*arguments)), atol=1e-4)


@pytest.mark.slow
def test_noise_of_a_sample_depends_only_on_its_key():
  keys = jax.random.split(jax.random.key(3), 3)
  batch = sampler.draw_noise(keys, (4, 6, 4), 5)
  single = sampler.draw_noise(keys[1:2], (4, 6, 4), 5)
  jax.tree.map(lambda b, s: np.testing.assert_array_equal(b[1:2], s), batch, single)
  assert batch.steps.shape == (3, 5, 4, 6, 4)
  assert not np.allclose(batch.latents[0], batch.latents[1])
  assert not np.allclose(batch.latents[0], batch.image_posterior[0])
