"""ControlNet residuals (scale, guess mode, pooling, SDXL) and UNet + ControlNet vs diffusers."""

import jax
import numpy as np
import pytest

from signerf_jax.diffusion import model_configs
from signerf_jax.diffusion.controlnet import guess_mode_scales, load_controlnet
from signerf_jax.diffusion.unet import load_unet
from signerf_jax.errors import InputError

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.parity
TOLERANCE = 1e-4


def nhwc(tensor) -> np.ndarray:
  return tensor.detach().numpy().transpose(0, 2, 3, 1)


def test_guess_mode_scales_match_torch_logspace():
  np.testing.assert_allclose(guess_mode_scales(7), torch.logspace(-1, 0, 7).numpy(), rtol=1e-6)


@pytest.mark.slow
@pytest.mark.parametrize("variant, guess_mode", [
    ("sd1", False), ("sdxl", True), ("pooled", True)])
def test_residuals_match_diffusers(reference_controlnets, reference_inputs, flax_inputs, variant,
                                   guess_mode):
  model, directory = reference_controlnets[variant]
  inputs = reference_inputs(model, 8, 12)
  with torch.no_grad():
    down, mid = model(**inputs, conditioning_scale=0.7, guess_mode=guess_mode, return_dict=False)
  module, params = load_controlnet(directory)
  apply = jax.jit(module.apply, static_argnames="guess_mode")
  residuals = apply({"params": params}, **flax_inputs(inputs), controlnet_conditioning_scale=0.7,
                    guess_mode=guess_mode)
  assert len(residuals.down) == len(down)
  for ours, theirs in zip(residuals.down + (residuals.mid,), list(down) + [mid]):
    assert ours.shape == nhwc(theirs).shape
    assert np.abs(nhwc(theirs)).max() > 1e-3  # Zero-convs were perturbed: nothing hides.
    np.testing.assert_allclose(np.asarray(ours), nhwc(theirs), atol=TOLERANCE, rtol=0)

  # A new conditioning scale is a new value, not a new program.
  apply({"params": params}, **flax_inputs(inputs), controlnet_conditioning_scale=0.3,
        guess_mode=guess_mode)
  assert apply._cache_size() == 1  # pylint: disable=protected-access


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["sd1", "sdxl"])
def test_unet_with_controlnet_matches_diffusers(reference_unets, reference_controlnets,
                                                reference_inputs, flax_inputs, variant):
  unet_model, unet_directory = reference_unets[variant]
  controlnet_model, controlnet_directory = reference_controlnets[variant]
  inputs = reference_inputs(controlnet_model, 8, 12, seed=2)
  with torch.no_grad():
    down, mid = controlnet_model(**inputs, conditioning_scale=0.8, return_dict=False)
    unet_inputs = {k: v for k, v in inputs.items() if k != "controlnet_cond"}
    expected = nhwc(unet_model(**unet_inputs, down_block_additional_residuals=down,
                               mid_block_additional_residual=mid).sample)

  controlnet, controlnet_params = load_controlnet(controlnet_directory)
  unet, unet_params = load_unet(unet_directory)

  @jax.jit
  def denoise(controlnet_params, unet_params, inputs):
    residuals = controlnet.apply({"params": controlnet_params}, **inputs,
                                 controlnet_conditioning_scale=0.8)
    unet_inputs = {k: v for k, v in inputs.items() if k != "controlnet_cond"}
    return unet.apply({"params": unet_params}, **unet_inputs, control=residuals)

  out = denoise(controlnet_params, unet_params, flax_inputs(inputs))
  np.testing.assert_allclose(np.asarray(out), expected, atol=TOLERANCE, rtol=0)


def test_wrong_conditioning_channels_are_input_errors(reference_controlnets, reference_inputs,
                                                      flax_inputs):
  model, directory = reference_controlnets["sd1"]
  module, params = load_controlnet(directory)
  inputs = flax_inputs(reference_inputs(model, 8, 12))
  inputs["controlnet_cond"] = inputs["controlnet_cond"][..., :1]
  with pytest.raises(InputError, match="controlnet_cond has 1 channels"):
    module.apply({"params": params}, **inputs)


def test_controlnet_config_rejects_per_block_layer_counts():
  with pytest.raises(InputError) as error:
    model_configs.ControlNetConfig.from_dict({"layers_per_block": [1, 2]}, "cn/config.json")
  assert error.value.field == "layers_per_block"
