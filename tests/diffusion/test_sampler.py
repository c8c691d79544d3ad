"""The compiled sampler: mask handling and paste-back against diffusers, noise, sheet-sized runs.

The full pipeline's parity with diffusers is in test_pipeline_parity.py.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from signerf_jax.clip import text as clip_text
from signerf_jax.diffusion import model_configs, sampler, schedulers, weights
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
    schedule = schedulers.make_schedule(config, num_steps)
    noise = sampler.draw_noise(jax.random.split(jax.random.key(0), 1),
                               (height // 4, width // 4, 4), num_steps)
    guidance = sampler.Guidance(jnp.float32(7.5),
                                jnp.asarray(sampler.controlnet_conditioning_scale_per_step(
                                    num_steps, 0.8)))
    return models, schedule, prompt, None, inputs, noise, guidance

  compiled = {steps: sampler.sample.lower(*arguments(steps), settings=settings).compile()
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


def test_noise_of_a_sample_depends_only_on_its_key():
  keys = jax.random.split(jax.random.key(3), 3)
  batch = sampler.draw_noise(keys, (4, 6, 4), 5)
  single = sampler.draw_noise(keys[1:2], (4, 6, 4), 5)
  jax.tree.map(lambda b, s: np.testing.assert_array_equal(b[1:2], s), batch, single)
  assert batch.steps.shape == (3, 5, 4, 6, 4)
  assert not np.allclose(batch.latents[0], batch.latents[1])
  assert not np.allclose(batch.latents[0], batch.image_posterior[0])


@pytest.mark.parametrize("num_steps, start, end, expected", [
    (3, 0.34, 1.0, [0, 0, 1]),  # 1/3 < 0.34: the second step is still off.
    (3, 0.0, 0.6, [1, 0, 0]),
    (4, 0.25, 0.75, [0, 1, 1, 0]),
    (2, 0.0, 1.0, [1, 1]),
])
def test_controlnet_scale_per_step_follows_diffusers_controlnet_keep(num_steps, start, end,
                                                                    expected):
  np.testing.assert_array_equal(
      sampler.controlnet_conditioning_scale_per_step(num_steps, 0.7, start, end),
      0.7 * np.asarray(expected, np.float32))


@pytest.mark.parametrize("start, end", [(0.5, 0.5), (-0.1, 1.0), (0.0, 1.2)])
def test_bad_control_guidance_is_an_input_error(start, end):
  with pytest.raises(InputError):
    sampler.controlnet_conditioning_scale_per_step(3, 1.0, start, end)


def test_mask_binarization_is_diffusers():
  mask = jnp.asarray([0.0, 0.49, 0.5, 0.51, 1.0])
  np.testing.assert_array_equal(sampler.binarize_mask(mask), [0, 0, 1, 1, 1])


@pytest.mark.parity
@pytest.mark.parametrize("size, latent_size", [
    ((32, 48), (4, 6)), ((30, 50), (7, 9)), ((17, 5), (4, 3)), ((8, 8), (16, 16))])
def test_mask_downsampling_matches_torch_nearest(size, latent_size):
  torch = pytest.importorskip("torch")
  mask = np.random.default_rng(1).random((2, *size, 1)).astype(np.float32)
  expected = torch.nn.functional.interpolate(torch.from_numpy(mask.transpose(0, 3, 1, 2)),
                                             size=latent_size).numpy().transpose(0, 2, 3, 1)
  np.testing.assert_array_equal(sampler.downsample_mask(jnp.asarray(mask), *latent_size), expected)


@pytest.mark.parity
@pytest.mark.parametrize("radius", [0, 1, 4, 9])
def test_blurred_paste_back_matches_diffusers_apply_overlay(radius):
  """diffusers' mask_processor.blur (PIL GaussianBlur) then apply_overlay, on 8-bit images;
  ours works in float, so they agree to PIL's rounding."""
  diffusers = pytest.importorskip("diffusers")
  from PIL import Image  # pylint: disable=g-import-not-at-top
  processor = diffusers.image_processor.VaeImageProcessor(
      do_normalize=False, do_binarize=True, do_convert_grayscale=True)
  rng = np.random.default_rng(radius)
  mask = np.zeros((40, 56), np.uint8)
  mask[10:30, 5:45] = 255
  mask[0:4, 50:] = 255  # Touching the border: PIL repeats edge pixels.
  original, generated = (rng.integers(0, 256, (40, 56, 3), np.uint8) for _ in range(2))

  blurred = processor.blur(Image.fromarray(mask), blur_factor=radius) if radius else \
      Image.fromarray(mask)
  expected = np.asarray(processor.apply_overlay(blurred, Image.fromarray(original),
                                                Image.fromarray(generated)), np.float32) / 255
  ours_mask = sampler.blur_mask(jnp.asarray(mask[None, ..., None] / 255, jnp.float32), radius)
  np.testing.assert_allclose(ours_mask[0, ..., 0], np.asarray(blurred, np.float32) / 255,
                             atol=1.5 / 255, rtol=0)
  ours = sampler.paste_back(jnp.asarray(original[None] / 255, jnp.float32),
                            jnp.asarray(generated[None] / 255, jnp.float32), ours_mask)
  np.testing.assert_allclose(ours[0], expected, atol=2.5 / 255, rtol=0)
  if radius:
    assert np.abs(np.asarray(ours_mask[0, ..., 0]) - mask / 255).max() > 0.3
