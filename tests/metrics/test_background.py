"""Background preservation: the paper's PSNR_bg / SSIM_bg and the background-only variant."""

import numpy as np
import pytest
from skimage.metrics import structural_similarity

from signerf_jax.metrics import background

NUM_VIEWS, HEIGHT, WIDTH = 3, 32, 40


def edited_views(seed=0, noise=0.05):
  """Originals, edits (selection replaced by new content, background slightly noisy) and masks
  covering 0%, ~25% and ~75% of the views."""
  rng = np.random.default_rng(seed)
  original = rng.uniform(0.2, 0.8, (NUM_VIEWS, HEIGHT, WIDTH, 3)).astype(np.float32)
  masks = np.zeros((NUM_VIEWS, HEIGHT, WIDTH), bool)
  masks[1, 8:24, 10:30] = True
  masks[2, :, :30] = True
  edited = np.clip(original + noise * rng.normal(size=original.shape), 0, 1).astype(np.float32)
  edited[masks] = rng.uniform(0, 1, (masks.sum(), 3))
  return original, edited, masks


def test_definitions_against_numpy_and_skimage():
  original, edited, masks = edited_views()
  per_view = background.per_view_background_preservation(original, edited, masks)
  for view in range(NUM_VIEWS):
    keep = ~masks[view]
    squared = (original[view] - edited[view])**2
    masked_squared = squared * keep[..., None]
    assert float(per_view["psnr_paper"][view]) == pytest.approx(
        10 * np.log10(1 / masked_squared.mean()), abs=1e-3)
    assert float(per_view["psnr_background"][view]) == pytest.approx(
        10 * np.log10(1 / squared[keep].mean()), abs=1e-3)
    masked = [image * keep[..., None] for image in (edited[view], original[view])]
    expected_ssim = structural_similarity(*masked, gaussian_weights=True, sigma=1.5,
                                          use_sample_covariance=False, data_range=1,
                                          channel_axis=-1)
    assert float(per_view["ssim_paper"][view]) == pytest.approx(expected_ssim, abs=1e-4)


def test_paper_definition_is_inflated_by_the_mask_share():
  """Masked pixels count as perfect matches: PSNR_paper - PSNR_background = -10 log10(share of
  background pixels), and the background-only values ignore the selection entirely."""
  original, edited, masks = edited_views()
  per_view = background.per_view_background_preservation(original, edited, masks)
  share = 1 - masks.mean(axis=(1, 2))
  np.testing.assert_allclose(per_view["psnr_paper"] - per_view["psnr_background"],
                             -10 * np.log10(share), atol=1e-3)
  assert per_view["ssim_paper"][2] > per_view["ssim_background"][2]
  # Changing the content inside the selection changes neither background-only value.
  _, other_edit, _ = edited_views(seed=0)
  other_edit[masks] = 1 - other_edit[masks]
  other = background.per_view_background_preservation(original, other_edit, masks)
  np.testing.assert_allclose(other["psnr_background"], per_view["psnr_background"], atol=1e-4)


def test_summary_means_and_views_without_background():
  original, edited, masks = edited_views()
  masks[0] = True  # No background left in view 0.
  per_view = background.per_view_background_preservation(original, edited, masks)
  assert np.isnan(per_view["psnr_background"][0]) and np.isnan(per_view["ssim_background"][0])
  summary = background.background_preservation(original, edited, masks)
  assert summary["num_views"] == NUM_VIEWS
  assert summary["psnr_background"] == pytest.approx(
      float(np.mean(per_view["psnr_background"][1:])), abs=1e-4)
  assert summary["psnr_paper"] == pytest.approx(float(np.mean(per_view["psnr_paper"])), abs=1e-4)
  assert summary["background_fraction"] == pytest.approx(1 - masks.mean())


def test_identical_backgrounds_and_no_recompilation():
  original, edited, masks = edited_views(noise=0.0)
  per_view = background.per_view_background_preservation(original, edited, masks)
  assert np.all(np.asarray(per_view["psnr_background"]) >= 99)  # The 1e-10 MSE floor.
  np.testing.assert_allclose(per_view["ssim_background"], 1.0, atol=1e-5)
  cache_size = background.per_view_background_preservation._cache_size()  # pylint: disable=protected-access
  background.per_view_background_preservation(edited, original, masks.astype(np.float32) > 0)
  assert background.per_view_background_preservation._cache_size() == cache_size  # pylint: disable=protected-access
