"""AutoencoderKL: encode (mode, sample with injected noise) and decode parity with diffusers."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from safetensors.numpy import load_file, save_file

from signerf_jax.diffusion import layers, model_configs
from signerf_jax.diffusion.vae import DiagonalGaussian, load_vae
from signerf_jax.errors import InputError

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.parity
TOLERANCE = 1e-4


def nhwc(tensor) -> np.ndarray:
  return tensor.detach().numpy().transpose(0, 2, 3, 1)


@pytest.mark.slow
@pytest.mark.parametrize("winograd", [False, True], ids=["direct", "winograd"])
def test_encode_and_decode_match_diffusers(reference_vae, monkeypatch, winograd):
  """`winograd` lowers the size thresholds so every 3x3 convolution takes that path."""
  if winograd:
    monkeypatch.setattr(layers, "CPU_WINOGRAD_MIN_TILES", 1)
    monkeypatch.setattr(layers, "CPU_WINOGRAD_MIN_CHANNELS", 1)
  model, directory = reference_vae
  generator = torch.Generator().manual_seed(0)
  images = torch.rand(2, 3, 16, 24, generator=generator) * 2 - 1
  with torch.no_grad():
    posterior = model.encode(images).latent_dist
    sampled = posterior.sample(generator=torch.Generator().manual_seed(5))
    decoded = model.decode(posterior.mode()).sample
  # The noise sample() drew, injected into ours.
  noise = torch.randn(posterior.mean.shape, generator=torch.Generator().manual_seed(5))

  module, params = load_vae(directory)
  encode = jax.jit(lambda p, x: module.apply({"params": p}, x, method=module.encode))
  decode = jax.jit(lambda p, z: module.apply({"params": p}, z, method=module.decode))
  ours = encode(params, jnp.asarray(nhwc(images)))
  np.testing.assert_allclose(np.asarray(ours.mode()), nhwc(posterior.mode()), atol=TOLERANCE,
                             rtol=0)
  np.testing.assert_allclose(np.asarray(ours.std), nhwc(posterior.std), atol=TOLERANCE, rtol=0)
  np.testing.assert_allclose(np.asarray(ours.sample_from_noise(jnp.asarray(nhwc(noise)))),
                             nhwc(sampled), atol=TOLERANCE, rtol=0)
  assert np.abs(nhwc(sampled) - nhwc(posterior.mode())).max() > 1e-2  # The noise mattered.
  np.testing.assert_allclose(np.asarray(decode(params, ours.mode())), nhwc(decoded),
                             atol=TOLERANCE, rtol=0)
  encode(params, jnp.asarray(nhwc(images)) * 0.5)
  assert encode._cache_size() == 1  # pylint: disable=protected-access


def test_latent_scaling_round_trips_with_shift(reference_vae):
  _, directory = reference_vae
  module, _ = load_vae(directory)
  config = module.config
  assert (config.scaling_factor, config.shift_factor) == (0.5, 0.25)
  z = jnp.linspace(-2, 2, 5)
  np.testing.assert_allclose(config.to_diffusion_latents(z), (z - 0.25) * 0.5)
  np.testing.assert_allclose(config.from_diffusion_latents(config.to_diffusion_latents(z)), z,
                             atol=1e-6)


def test_sample_uses_the_key_deterministically():
  posterior = DiagonalGaussian.from_moments(jnp.concatenate(
      [jnp.zeros((1, 2, 2, 4)), jnp.full((1, 2, 2, 4), 100.0)], axis=-1))
  assert float(posterior.logvar.max()) == 20.0  # Clamped as diffusers.
  first, again = (posterior.sample(jax.random.key(1)) for _ in range(2))
  np.testing.assert_array_equal(first, again)
  assert not np.allclose(first, posterior.sample(jax.random.key(2)))


def test_legacy_attention_names_load(reference_vae, tmp_path):
  model, directory = reference_vae
  tensors = load_file(directory / "diffusion_pytorch_model.safetensors")
  legacy = {"to_q": "query", "to_k": "key", "to_v": "value", "to_out.0": "proj_attn"}
  renamed = {}
  for name, tensor in tensors.items():
    for new, old in legacy.items():
      name = name.replace(f"attentions.0.{new}.", f"attentions.0.{old}.")
    renamed[name] = tensor
  assert "encoder.mid_block.attentions.0.proj_attn.weight" in renamed
  save_file(renamed, tmp_path / "diffusion_pytorch_model.safetensors")
  (tmp_path / "config.json").write_text((directory / "config.json").read_text())
  _, params = load_vae(tmp_path)
  _, expected = load_vae(directory)
  jax.tree.map(np.testing.assert_array_equal, params, expected)


def test_config_rejects_latent_statistics():
  with pytest.raises(InputError) as error:
    model_configs.AutoencoderConfig.from_dict({"latents_mean": [0.0] * 4}, "vae/config.json")
  assert error.value.field == "latents_mean"
