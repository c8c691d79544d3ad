"""Fixtures for the diffusion tests: tiny random diffusers models saved as safetensors.

Each fixture builds a small PyTorch model (block_out_channels (32, 64) as diffusers' own tests),
perturbs *every* parameter with noise (diffusers zero-initialises zero-convs and some output
convolutions; a wrong mapping must not hide behind zeros), saves it with
`save_pretrained(..., safe_serialization=True)` and returns the model with its directory.
"""

from __future__ import annotations

import jax.numpy as jnp
import pytest

TINY_BACKBONE = dict(block_out_channels=(32, 64), cross_attention_dim=32, norm_num_groups=8,
                     down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"))
TINY_UNET = dict(TINY_BACKBONE, up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
                 layers_per_block=2, attention_head_dim=4)
TINY_VARIANTS = {
    "sd1": dict(TINY_UNET),
    "inpaint": dict(TINY_UNET, in_channels=9, layers_per_block=1),
    # SD 2.x: linear projections, upcast attention, heads per block as a list.
    "sd2": dict(TINY_UNET, use_linear_projection=True, upcast_attention=True,
                attention_head_dim=[2, 4], layers_per_block=1),
    # SDXL: text_time embedding from pooled text (16) and 6 time ids x 8, several
    # transformer layers in a block, no attention in the first block.
    "sdxl": dict(TINY_UNET, use_linear_projection=True, attention_head_dim=[2, 4],
                 layers_per_block=1,
                 down_block_types=("DownBlock2D", "CrossAttnDownBlock2D"),
                 up_block_types=("CrossAttnUpBlock2D", "UpBlock2D"),
                 transformer_layers_per_block=[1, 2], addition_embed_type="text_time",
                 addition_time_embed_dim=8, projection_class_embeddings_input_dim=16 + 6 * 8),
}


def perturb(model, seed: int):
  """Adds N(0, 0.1^2) noise to every parameter in place; returns the model in eval mode."""
  import torch  # pylint: disable=g-import-not-at-top
  generator = torch.Generator().manual_seed(seed)
  with torch.no_grad():
    for parameter in model.parameters():
      parameter.add_(0.1 * torch.randn(parameter.shape, generator=generator))
  return model.eval()


def save_model(model, directory):
  model.save_pretrained(directory, safe_serialization=True)
  return model, directory


@pytest.fixture(scope="session")
def perturb_parameters():
  """perturb(model, seed), for tests that build their own reference models."""
  return perturb


@pytest.fixture(scope="session")
def diffusers():
  pytest.importorskip("torch")
  return pytest.importorskip("diffusers")


@pytest.fixture(scope="session")
def reference_unets(diffusers, tmp_path_factory):
  """{variant: (torch UNet2DConditionModel, directory)} for the TINY_VARIANTS."""
  import torch  # pylint: disable=g-import-not-at-top
  models = {}
  for seed, (variant, options) in enumerate(TINY_VARIANTS.items()):
    torch.manual_seed(seed)
    model = perturb(diffusers.UNet2DConditionModel(**options), seed)
    models[variant] = save_model(model, tmp_path_factory.mktemp(f"unet_{variant}"))
  return models


@pytest.fixture(scope="session")
def reference_controlnets(diffusers, tmp_path_factory):
  """{variant: (torch ControlNetModel, directory)}: "sd1" (matches the sd1 UNet), "sdxl"
  (text_time, matches the sdxl UNet) and "pooled" (global_pool_conditions, BGR)."""
  import torch  # pylint: disable=g-import-not-at-top
  sdxl = TINY_VARIANTS["sdxl"]
  variants = {
      "sd1": dict(TINY_BACKBONE, layers_per_block=2, attention_head_dim=4,
                  conditioning_embedding_out_channels=(8, 16)),
      "sdxl": dict(TINY_BACKBONE, layers_per_block=1, conditioning_embedding_out_channels=(8, 16),
                   **{name: sdxl[name] for name in (
                       "attention_head_dim", "down_block_types", "use_linear_projection",
                       "transformer_layers_per_block", "addition_embed_type",
                       "addition_time_embed_dim", "projection_class_embeddings_input_dim")}),
      "pooled": dict(TINY_BACKBONE, layers_per_block=1, attention_head_dim=4,
                     conditioning_embedding_out_channels=(8, 16, 16),
                     global_pool_conditions=True, controlnet_conditioning_channel_order="bgr"),
  }
  models = {}
  for seed, (variant, options) in enumerate(variants.items()):
    torch.manual_seed(100 + seed)
    model = perturb(diffusers.ControlNetModel(**options), 100 + seed)
    models[variant] = save_model(model, tmp_path_factory.mktemp(f"controlnet_{variant}"))
  return models


@pytest.fixture(scope="session")
def reference_vae(diffusers, tmp_path_factory):
  """(torch AutoencoderKL, directory) with two blocks (one downsampling), shift_factor set."""
  import torch  # pylint: disable=g-import-not-at-top
  torch.manual_seed(7)
  model = perturb(diffusers.AutoencoderKL(
      block_out_channels=(32, 64), down_block_types=("DownEncoderBlock2D",) * 2,
      up_block_types=("UpDecoderBlock2D",) * 2, layers_per_block=1, latent_channels=4,
      norm_num_groups=8, scaling_factor=0.5, shift_factor=0.25), 7)
  return save_model(model, tmp_path_factory.mktemp("vae"))


def _reference_inputs(model, height, width, seed=0):
  """Torch keyword inputs for a UNet or ControlNet forward: two random latents of
  height x width, timesteps (3, 921), five text tokens, SDXL's text_time extras when the model
  takes them, and for a ControlNet a [0, 1] conditioning image at its embedding's scale."""
  import torch  # pylint: disable=g-import-not-at-top
  generator = torch.Generator().manual_seed(seed)
  config = model.config
  inputs = dict(sample=torch.randn(2, config.in_channels, height, width, generator=generator),
                timestep=torch.tensor([3, 921]),
                encoder_hidden_states=torch.randn(2, 5, config.cross_attention_dim,
                                                  generator=generator))
  if config.addition_embed_type == "text_time":
    pooled = config.projection_class_embeddings_input_dim - 6 * config.addition_time_embed_dim
    inputs["added_cond_kwargs"] = dict(
        text_embeds=torch.randn(2, pooled, generator=generator),
        time_ids=torch.tensor([[512, 768, 0, 0, 512, 768], [1024, 1024, 16, 32, 1024, 1024]]))
  if "conditioning_embedding_out_channels" in config:
    factor = 2 ** (len(config.conditioning_embedding_out_channels) - 1)
    inputs["controlnet_cond"] = torch.rand(2, config.conditioning_channels, height * factor,
                                           width * factor, generator=generator)
  return inputs


def _flax_inputs(inputs):
  """The same inputs as keyword arguments of our modules (NHWC, SDXL extras by name)."""
  names = dict(sample="sample", timestep="timesteps", encoder_hidden_states="encoder_hidden_states",
               controlnet_cond="controlnet_cond")
  as_array = lambda value: value.numpy().transpose(0, 2, 3, 1) if value.ndim == 4 else value.numpy()
  converted = {names[name]: jnp.asarray(as_array(value)) for name, value in inputs.items()
               if name in names}
  for name, value in inputs.get("added_cond_kwargs", {}).items():
    converted[name] = jnp.asarray(value.numpy(), jnp.float32)
  return converted


@pytest.fixture(scope="session")
def reference_inputs():
  """_reference_inputs(model, height, width, seed=0) -> torch keyword inputs."""
  return _reference_inputs


@pytest.fixture(scope="session")
def flax_inputs():
  """_flax_inputs(torch inputs) -> our keyword inputs."""
  return _flax_inputs
