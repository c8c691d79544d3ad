"""VGG-LPIPS in Flax against the lpips package's code, on random backbone and linear weights.

The reference is `lpips_reference`: lpips 0.1.4's own LPIPS / ScalingLayer / NetLinLayer /
normalize_tensor / spatial_average / vgg16 code, with torchvision's `vgg16().features` replaced by
an architecturally identical plain-torch Sequential, because no torchvision wheel from PyPI loads
next to the CPU torch used here (see that module's docstring). When the real `lpips` package (and
so a working torchvision) is importable, `test_matches_installed_lpips_package` also compares
against it, and `test_vgg_stand_in_matches_torchvision` checks the substitute layer by layer.
"""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from safetensors.numpy import save_file

from signerf_jax.errors import InputError
from signerf_jax.metrics import lpips

torch = pytest.importorskip("torch")
import lpips_reference  # pylint: disable=g-import-not-at-top,wrong-import-position

pytestmark = pytest.mark.parity

TOLERANCE = dict(atol=1e-5, rtol=0)
BATCH, HEIGHT, WIDTH = 3, 32, 24


def randomized(model, seed):
  """Every weight perturbed: backbone weights scaled by 1 + N(0, 0.2^2), biases N(0, 0.05^2)
  (torchvision initialises them to zero), lin weights |N(0, 1)| (trained ones are >= 0)."""
  generator = torch.Generator().manual_seed(seed)
  with torch.no_grad():
    for name, parameter in model.named_parameters():
      noise = torch.randn(parameter.shape, generator=generator)
      if name.startswith("lin"):
        parameter.copy_(noise.abs())
      elif name.endswith("bias"):
        parameter.copy_(0.05 * noise)
      else:
        parameter.mul_(1 + 0.2 * noise)
  return model.eval()


def flax_tensors(model) -> dict[str, np.ndarray]:
  """The reference's state dict under the names `metrics.lpips` loads: torchvision's
  `features.N.*` for the backbone (lpips nests them as `net.sliceK.N.*`), lpips' `linK.*`."""
  tensors = {}
  for name, value in model.state_dict().items():
    if name.startswith("net."):
      name = "features." + name.split(".", 2)[-1]
    elif not re.fullmatch(r"lin\d\.model\.1\.weight", name):
      continue  # The ScalingLayer's constants, and `lins.K.*` (the same tensors as `linK.*`).
    tensors[name] = value.numpy()
  return tensors


@pytest.fixture(scope="module")
def reference():
  torch.manual_seed(0)
  return randomized(lpips_reference.LPIPS(pretrained=False, net="vgg", pnet_rand=True,
                                          verbose=False), seed=0)


@pytest.fixture(scope="module")
def weights_file(reference, tmp_path_factory):
  path = tmp_path_factory.mktemp("lpips") / "lpips_vgg.safetensors"
  save_file(flax_tensors(reference), str(path))
  return path


@pytest.fixture(scope="module")
def params(weights_file):
  return lpips.load_lpips_params(weights_file)


def image_pairs(seed=0):
  """[B, H, W, 3] pairs in [0, 1]: smooth random images, noisy copies, and one identical pair."""
  rng = np.random.default_rng(seed)
  images = rng.uniform(0, 1, (BATCH, HEIGHT // 4, WIDTH // 4, 3))
  images = np.repeat(np.repeat(images, 4, axis=1), 4, axis=2)
  references = np.clip(images + 0.1 * rng.normal(size=images.shape), 0, 1)
  references[-1] = images[-1]
  return images.astype(np.float32), references.astype(np.float32)


def reference_distance(model, images, references):
  as_torch = lambda array: torch.from_numpy(np.ascontiguousarray(array.transpose(0, 3, 1, 2)))
  with torch.no_grad():
    return model(as_torch(images), as_torch(references), normalize=True).numpy().reshape(-1)


def test_distances_match_reference(reference, params):
  images, references = image_pairs()
  expected = reference_distance(reference, images, references)
  ours = np.asarray(lpips.lpips_distance(params, images, references))
  assert expected[:-1].min() > 0.05  # Random weights still give clearly non-zero distances.
  np.testing.assert_allclose(ours, expected, **TOLERANCE)
  assert ours[-1] < 1e-10  # Identical images.


@pytest.mark.slow
def test_gradients_match_reference_and_are_finite(reference, params):
  images, references = image_pairs(1)
  torch_images = torch.from_numpy(images.transpose(0, 3, 1, 2)).requires_grad_()
  reference(torch_images, torch.from_numpy(references.transpose(0, 3, 1, 2)),
            normalize=True).sum().backward()
  expected = torch_images.grad.numpy().transpose(0, 2, 3, 1)
  gradient = jax.jit(jax.grad(lambda x: jnp.sum(lpips.lpips_distance(params, x, references))))
  ours = np.asarray(gradient(images))
  scale = np.abs(expected).max()
  np.testing.assert_allclose(ours, expected, atol=1e-4 * scale, rtol=0)
  # Flat black images give all-zero ReLU features; the package's torch.sqrt has an infinite
  # derivative there, our norm a finite one.
  black = np.zeros_like(images)
  assert np.isfinite(np.asarray(gradient(black))).all()


def test_no_recompilation_for_new_images(params):
  images, references = image_pairs(2)
  lpips.lpips_distance(params, images, references)
  cache_size = lpips.lpips_distance._cache_size()  # pylint: disable=protected-access
  lpips.lpips_distance(params, references, images)
  assert lpips.lpips_distance._cache_size() == cache_size  # pylint: disable=protected-access


def test_conversion_script_reads_torchvision_and_lpips_files(reference, params, tmp_path,
                                                             experiment_script):
  tensors = {name: torch.from_numpy(value) for name, value in flax_tensors(reference).items()}
  vgg16 = {name: value for name, value in tensors.items() if name.startswith("features.")}
  vgg16["classifier.6.bias"] = torch.zeros(1000)  # Present in torchvision's file, not needed.
  torch.save(vgg16, tmp_path / "vgg16.pth")
  torch.save({name: value for name, value in tensors.items() if name.startswith("lin")},
             tmp_path / "vgg.pth")
  script = experiment_script("convert_lpips_weights")
  output = tmp_path / "out" / "lpips.safetensors"
  assert script.main(["--vgg16", str(tmp_path / "vgg16.pth"), "--lin", str(tmp_path / "vgg.pth"),
                      "--output", str(output)]) == 0
  converted = lpips.load_lpips_params(output)
  jax.tree.map(np.testing.assert_array_equal, converted, params)


def test_missing_or_misshapen_tensors_are_named(reference, tmp_path):
  tensors = flax_tensors(reference)
  del tensors["lin3.model.1.weight"]
  save_file(tensors, str(tmp_path / "missing.safetensors"))
  with pytest.raises(InputError, match=r"missing tensor lin3\.model\.1\.weight"):
    lpips.load_lpips_params(tmp_path / "missing.safetensors")
  tensors = flax_tensors(reference)
  tensors["features.5.weight"] = tensors["features.5.weight"][:, :32]
  save_file(tensors, str(tmp_path / "misshapen.safetensors"))
  with pytest.raises(InputError, match=r"features\.5\.weight has shape \(128, 32, 3, 3\)"):
    lpips.load_lpips_params(tmp_path / "misshapen.safetensors")


def test_images_smaller_than_the_deepest_tap_are_refused(params):
  small = np.zeros((1, 15, 32, 3), np.float32)
  with pytest.raises(ValueError, match="at least 16 pixels"):
    lpips.lpips_distance(params, small, small)


def test_vgg_stand_in_matches_torchvision():
  try:
    import torchvision  # pylint: disable=g-import-not-at-top
  except (ImportError, RuntimeError, OSError) as error:
    pytest.skip(f"torchvision does not import here ({error})")
  theirs = torchvision.models.vgg16().features
  ours = lpips_reference.vgg16_features()
  assert [type(module) for module in ours] == [type(module) for module in theirs]
  assert {name: value.shape for name, value in ours.state_dict().items()} == {
      name: value.shape for name, value in theirs.state_dict().items()}


def test_matches_installed_lpips_package(params, weights_file):
  try:
    import lpips as lpips_package  # pylint: disable=g-import-not-at-top
  except (ImportError, RuntimeError, OSError) as error:
    pytest.skip(f"the lpips package does not import here ({error})")
  model = lpips_package.LPIPS(net="vgg", pretrained=False, pnet_rand=True, verbose=False).eval()
  from safetensors.torch import load_file  # pylint: disable=g-import-not-at-top
  tensors = load_file(weights_file)
  with torch.no_grad():
    for name, parameter in model.named_parameters():
      source = "features." + name.split(".", 2)[-1] if name.startswith("net.") else name
      parameter.copy_(tensors[source])
  images, references = image_pairs(3)
  np.testing.assert_allclose(np.asarray(lpips.lpips_distance(params, images, references)),
                             reference_distance(model, images, references), **TOLERANCE)
