import numpy as np
import pytest
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from signerf_jax.metrics import image


def noisy_pair(seed, height=37, width=45, noise=0.1):
  rng = np.random.default_rng(seed)
  reference = rng.uniform(0, 1, (height, width, 3)).astype(np.float32)
  # Smooth structure plus noise, so that SSIM is neither ~0 nor ~1.
  reference = (reference + np.roll(reference, 1, 0) + np.roll(reference, 1, 1)) / 3
  distorted = np.clip(reference + noise * rng.normal(size=reference.shape), 0, 1)
  return distorted.astype(np.float32), reference


@pytest.mark.parametrize("seed, noise", [(0, 0.02), (1, 0.1), (2, 0.3)])
def test_ssim_matches_skimage(seed, noise):
  distorted, reference = noisy_pair(seed, noise=noise)
  expected = structural_similarity(distorted, reference, gaussian_weights=True, sigma=1.5,
                                   use_sample_covariance=False, data_range=1, channel_axis=-1)
  assert float(image.ssim(distorted, reference)) == pytest.approx(expected, abs=1e-4)


def test_ssim_of_identical_images_is_one_and_mask_selects_region():
  distorted, reference = noisy_pair(3)
  assert float(image.ssim(reference, reference)) == pytest.approx(1.0, abs=1e-5)
  half = reference.copy()
  half[:, 22:] = distorted[:, 22:]
  mask = np.zeros(reference.shape[:2], np.float32)
  mask[:, :12] = 1  # far from the changed half (window radius 5)
  assert float(image.ssim(half, reference, mask)) == pytest.approx(1.0, abs=1e-5)
  assert float(image.ssim(half, reference, 1 - mask)) < 0.99


def test_psnr_matches_skimage_and_masks():
  distorted, reference = noisy_pair(4)
  expected = peak_signal_noise_ratio(reference, distorted, data_range=1)
  assert float(image.psnr(distorted, reference)) == pytest.approx(expected, abs=1e-3)
  mask = np.zeros(reference.shape[:2], np.float32)
  mask[:10] = 1
  expected_masked = 10 * np.log10(1 / np.mean((distorted[:10] - reference[:10])**2))
  assert float(image.psnr(distorted, reference, mask)) == pytest.approx(expected_masked, abs=1e-3)
  assert np.isfinite(float(image.psnr(reference, reference)))
