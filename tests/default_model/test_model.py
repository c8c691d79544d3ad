"""The default model's architecture: configs that the real loaders (and diffusers) accept, the
ControlNet's starting point, and the parameter budget."""

import dataclasses
from pathlib import Path

import jax
import numpy as np
import pytest

from signerf_jax.default_model import model
from signerf_jax.diffusion import weights

MAX_SHIPPED_BYTES = 40 * 2**20
VOCAB_SIZE = 48  # The default dataset's vocabulary is about 40 words.


@pytest.fixture(scope="module")
def default_components():
  return model.build(model.Architecture(), VOCAB_SIZE)


def test_configs_parse_and_fit_together(default_components):
  architecture = model.Architecture()
  assert architecture.latent_factor == 4
  unet, controlnet, vae = (default_components.unet.config, default_components.controlnet.config,
                           default_components.vae.config)
  assert unet.in_channels == 2 * vae.latent_channels + 1 == 9
  assert controlnet.block_out_channels == unet.block_out_channels
  assert unet.cross_attention_dim == default_components.text.hidden_size
  assert default_components.text.eos_token_id == 3 and default_components.text.pad_token_id == 0
  with pytest.raises(ValueError, match="downsamples"):
    dataclasses.replace(architecture, conditioning_embedding_channels=(16, 32)).check()


@pytest.mark.parity
def test_diffusers_and_transformers_build_the_same_parameters(default_components):
  """The config dicts mean to diffusers / transformers what they mean to our loaders: every
  tensor name and shape of the reference models is what our loaders expect."""
  diffusers = pytest.importorskip("diffusers")
  transformers = pytest.importorskip("transformers")
  from signerf_jax.clip import text as clip_text  # pylint: disable=g-import-not-at-top
  architecture = model.Architecture()
  references = {
      "unet": (diffusers.UNet2DConditionModel, architecture.unet_config(),
               default_components.unet),
      "controlnet": (diffusers.ControlNetModel, architecture.controlnet_config(),
                     default_components.controlnet),
      "vae": (diffusers.AutoencoderKL, architecture.vae_config(), default_components.vae)}
  for name, (reference_class, config, module) in references.items():
    reference = reference_class.from_config(config)
    shapes = {key: tuple(value.shape) for key, value in reference.state_dict().items()}
    assert shapes == weights.expected_shapes(module), name
  text_config = architecture.text_encoder_config(VOCAB_SIZE)
  reference = transformers.CLIPTextModel(transformers.CLIPTextConfig(**text_config))
  shapes = {key: tuple(value.shape) for key, value in reference.state_dict().items()
            if not key.endswith("position_ids")}
  assert shapes == clip_text.expected_shapes(default_components.text, prefix="")


@pytest.mark.slow
def test_initial_controlnet_adds_nothing(tiny_architecture):
  """It starts as a copy of the UNet's down path whose residuals are all zero (so the UNet's
  output is unchanged at any scale)."""
  components = model.build(tiny_architecture, VOCAB_SIZE)
  unet_params = model.init_unet(components, np.random.default_rng(0))
  controlnet_params = model.init_controlnet(components, unet_params, np.random.default_rng(1))
  np.testing.assert_array_equal(controlnet_params["down_blocks_1"]["attentions_0"]["proj_in"]
                                ["kernel"], unet_params["down_blocks_1"]["attentions_0"]["proj_in"]
                                ["kernel"])
  np.testing.assert_array_equal(controlnet_params["conv_in"]["kernel"],
                                unet_params["conv_in"]["kernel"][:, :, :4])
  key = jax.random.key(0)
  residuals = jax.jit(components.controlnet.apply)(
      {"params": controlnet_params}, jax.random.normal(key, (1, 8, 8, 4)), 10.0,
      jax.random.normal(key, (1, 16, tiny_architecture.text_hidden_size)),
      jax.random.uniform(key, (1, 16, 16, 3)), 1.0)
  assert len(residuals.down) == 1 + 2 * tiny_architecture.unet_layers_per_block + 1
  assert all(not np.any(np.asarray(residual)) for residual in (*residuals.down, residuals.mid))


def test_parameter_budget(default_components):
  """The shipped model stays within ~40 MB in float16 (and so does the shipped directory)."""
  rng = np.random.default_rng(0)
  counts = {"vae": model.init_vae(default_components, rng),
            "unet": model.init_unet(default_components, rng),
            "text_encoder": model.init_text_encoder(default_components, rng)}
  counts["controlnet"] = model.init_controlnet(default_components, counts["unet"], rng)
  total = sum(model.parameter_count(params) for params in counts.values())
  assert 2 * total <= MAX_SHIPPED_BYTES, f"{total} parameters"
  shipped = Path(model.__file__).resolve().parent / "weights"
  if shipped.is_dir():
    size = sum(path.stat().st_size for path in shipped.rglob("*") if path.is_file())
    assert size <= MAX_SHIPPED_BYTES, f"{shipped} holds {size} bytes"
