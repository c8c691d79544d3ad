"""UNet2DCondition: config parsing, weight loading errors, parity with diffusers, no recompiles."""

import json

import jax
import ml_dtypes
import numpy as np
import pytest
from flax import traverse_util
from safetensors.numpy import save_file

from signerf_jax.diffusion import model_configs, weights
from signerf_jax.diffusion.unet import UNet2DCondition, load_unet
from signerf_jax.errors import InputError

TOLERANCE = 1e-4
TINY_CONFIG = {
    "_class_name": "UNet2DConditionModel", "block_out_channels": [32, 64],
    "cross_attention_dim": 32, "norm_num_groups": 8, "attention_head_dim": 4,
    "layers_per_block": 1, "down_block_types": ["CrossAttnDownBlock2D", "DownBlock2D"],
    "up_block_types": ["UpBlock2D", "CrossAttnUpBlock2D"]}


def nhwc(tensor) -> np.ndarray:
  return tensor.detach().numpy().transpose(0, 2, 3, 1)


def save_component(directory, config, params, dtype=np.float32):
  """Writes Flax params as a diffusers component (config.json + safetensors in torch layout)."""
  directory.mkdir(parents=True, exist_ok=True)
  (directory / "config.json").write_text(json.dumps(config))
  tensors = {weights.reference_name(path): weights.to_reference_layout(path, np.asarray(value))
             .astype(dtype) for path, value in traverse_util.flatten_dict(params).items()}
  save_file(tensors, directory / "diffusion_pytorch_model.safetensors")
  return tensors


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
  """A tiny UNet's random params, saved as a diffusers component (no torch needed)."""
  module = UNet2DCondition(model_configs.UNetConfig.from_dict(TINY_CONFIG))
  params = weights.random_params(module, seed=3)
  directory = tmp_path_factory.mktemp("tiny") / "unet"
  tensors = save_component(directory, TINY_CONFIG, params)
  return directory, params, tensors


def test_loads_what_was_saved_and_accepts_pipeline_directories(tiny_checkpoint):
  directory, params, _ = tiny_checkpoint
  for path in (directory, directory.parent):
    _, loaded = load_unet(path)
    jax.tree.map(np.testing.assert_array_equal, loaded, params)


def test_half_precision_weights_load_exactly(tiny_checkpoint, tmp_path):
  _, params, _ = tiny_checkpoint
  save_component(tmp_path, TINY_CONFIG, params, dtype=np.float16)
  _, loaded = load_unet(tmp_path, dtype=ml_dtypes.bfloat16)
  expected = jax.tree.map(lambda x: np.asarray(x).astype(np.float16).astype(ml_dtypes.bfloat16),
                          params)
  jax.tree.map(np.testing.assert_array_equal, loaded, expected)


@pytest.mark.parametrize("change, message, field", [
    (lambda t: t.pop("conv_in.weight"), r"missing tensor conv_in.weight \(expected shape "
     r"\(32, 4, 3, 3\)", "conv_in.weight"),
    (lambda t: t.update(extra=np.zeros(3, np.float32)), r"unexpected tensor extra with shape "
     r"\(3,\)", "extra"),
    (lambda t: t.update({"down_blocks.0.attentions.0.proj_in.weight": np.zeros((32, 32),
                                                                               np.float32)}),
     r"proj_in.weight has shape \(32, 32\) but the config needs \(32, 32, 1, 1\)",
     "down_blocks.0.attentions.0.proj_in.weight"),
])
def test_weight_mismatches_name_the_tensor_and_both_shapes(tiny_checkpoint, tmp_path, change,
                                                           message, field):
  directory, _, tensors = tiny_checkpoint
  tensors = dict(tensors)
  change(tensors)
  (tmp_path / "config.json").write_text(json.dumps(TINY_CONFIG))
  save_file(tensors, tmp_path / "diffusion_pytorch_model.safetensors")
  with pytest.raises(InputError, match=message) as error:
    load_unet(tmp_path)
  assert error.value.field == field
  assert error.value.path == str(tmp_path / "diffusion_pytorch_model.safetensors")


def test_missing_files_are_input_errors(tiny_checkpoint, tmp_path):
  with pytest.raises(InputError, match="no config.json"):
    load_unet(tmp_path)
  (tmp_path / "config.json").write_text(json.dumps(TINY_CONFIG))
  with pytest.raises(InputError, match="no .safetensors weights"):
    load_unet(tmp_path)


@pytest.mark.parametrize("override, field", [
    ({"resnet_time_scale_shift": "scale_shift"}, "resnet_time_scale_shift"),
    ({"made_up_option": 1}, "made_up_option"),
    ({"attention_head_dim": [4, 4, 4]}, "attention_head_dim"),
    ({"attention_head_dim": 5}, "attention_head_dim"),
    ({"down_block_types": ["AttnDownBlock2D", "DownBlock2D"]}, "down_block_types"),
    ({"addition_embed_type": "text_time"}, "addition_time_embed_dim"),
    ({"num_attention_heads": 4}, "num_attention_heads"),
    ({"norm_num_groups": 12}, "norm_num_groups"),
])
def test_unsupported_configs_name_the_field(override, field):
  with pytest.raises(InputError) as error:
    model_configs.UNetConfig.from_dict({**TINY_CONFIG, **override}, "unet/config.json")
  assert error.value.field == field and error.value.path == "unet/config.json"


def test_head_counts_follow_diffusers_naming():
  config = model_configs.UNetConfig.from_dict({**TINY_CONFIG, "attention_head_dim": [2, 4]})
  assert config.num_attention_heads == (2, 4)  # "attention_head_dim" holds head *counts*.
  assert config.time_embedding_dim == 128


@pytest.mark.slow
@pytest.mark.parity
@pytest.mark.parametrize("variant, height, width", [
    ("sd1", 16, 16), ("inpaint", 15, 10), ("sd2", 8, 8), ("sdxl", 8, 8)])
def test_matches_diffusers_and_compiles_once(reference_unets, reference_inputs, flax_inputs,
                                             variant, height, width):
  """Odd sizes (15 x 10) exercise diffusers' forced upsample sizes."""
  import torch  # pylint: disable=g-import-not-at-top
  model, directory = reference_unets[variant]
  inputs = reference_inputs(model, height, width)
  with torch.no_grad():
    expected = nhwc(model(**inputs).sample)
  module, params = load_unet(directory)
  apply = jax.jit(module.apply)
  out = apply({"params": params}, **flax_inputs(inputs))
  assert out.shape == expected.shape
  np.testing.assert_allclose(np.asarray(out), expected, atol=TOLERANCE, rtol=0)

  other = apply({"params": params}, **flax_inputs(reference_inputs(model, height, width, seed=1)))
  assert apply._cache_size() == 1  # pylint: disable=protected-access
  assert not np.allclose(other, out)
