"""Mask processing: binarisation, downsampling and the blurred paste-back against diffusers."""

import jax.numpy as jnp
import numpy as np
import pytest

from signerf_jax.diffusion import mask_processing


def test_mask_binarization_is_diffusers():
  mask = jnp.asarray([0.0, 0.49, 0.5, 0.51, 1.0])
  np.testing.assert_array_equal(mask_processing.binarize_mask(mask), [0, 0, 1, 1, 1])


@pytest.mark.parity
@pytest.mark.parametrize("size, latent_size", [
    ((32, 48), (4, 6)), ((30, 50), (7, 9)), ((17, 5), (4, 3)), ((8, 8), (16, 16))])
def test_mask_downsampling_matches_torch_nearest(size, latent_size):
  torch = pytest.importorskip("torch")
  mask = np.random.default_rng(1).random((2, *size, 1)).astype(np.float32)
  expected = torch.nn.functional.interpolate(torch.from_numpy(mask.transpose(0, 3, 1, 2)),
                                             size=latent_size).numpy().transpose(0, 2, 3, 1)
  np.testing.assert_array_equal(mask_processing.downsample_mask(jnp.asarray(mask), *latent_size),
                                expected)


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
  ours_mask = mask_processing.blur_mask(jnp.asarray(mask[None, ..., None] / 255, jnp.float32),
                                        radius)
  np.testing.assert_allclose(ours_mask[0, ..., 0], np.asarray(blurred, np.float32) / 255,
                             atol=1.5 / 255, rtol=0)
  ours = mask_processing.paste_back(jnp.asarray(original[None] / 255, jnp.float32),
                                    jnp.asarray(generated[None] / 255, jnp.float32), ours_mask)
  np.testing.assert_allclose(ours[0], expected, atol=2.5 / 255, rtol=0)
  if radius:
    assert np.abs(np.asarray(ours_mask[0, ..., 0]) - mask / 255).max() > 0.3
