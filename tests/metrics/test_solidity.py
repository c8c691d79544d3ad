"""Fit, solidity and bootstrap intervals on constructed cases, independent of any model:
identical views fit perfectly and a solid object scores 1; random views and a haze score low;
intervals separate only what differs."""

import numpy as np
import pytest

from signerf_jax.errors import InputError
from signerf_jax.metrics import solidity

RNG = np.random.default_rng(0)
VIEWS, SIZE = 6, 16


def disc_silhouettes(radius: float = 5.0) -> np.ndarray:
  y, x = np.mgrid[:SIZE, :SIZE] + 0.5
  disc = (x - SIZE / 2)**2 + (y - SIZE / 2)**2 < radius**2
  return np.repeat(disc[None], VIEWS, axis=0)


def test_identical_views_fit_perfectly_and_random_views_do_not():
  images = RNG.uniform(size=(VIEWS, SIZE, SIZE, 3))
  masks = disc_silhouettes()
  perfect = solidity.masked_psnr(images, images, masks)
  assert np.all(perfect == solidity.MAX_PSNR_DB)
  random = solidity.masked_psnr(RNG.uniform(size=images.shape), images, masks)
  assert np.all(random < 10.0)


def test_only_pixels_inside_the_mask_count_and_an_empty_mask_is_nan():
  images = np.zeros((VIEWS, SIZE, SIZE, 3))
  masks = disc_silhouettes()
  off_mask = np.where(masks[..., None], images, 1.0)  # Wrong only outside the masks.
  assert np.all(solidity.masked_psnr(off_mask, images, masks) == solidity.MAX_PSNR_DB)
  masks[2] = False
  psnr = solidity.masked_psnr(images + 0.1, images, masks)
  assert np.isnan(psnr[2]) and np.allclose(np.delete(psnr, 2), 20.0)


def test_a_solid_object_scores_one_and_a_haze_scores_low():
  shown = disc_silhouettes()
  solid = solidity.solidity(shown.astype(float), shown)
  assert np.all(solid["iou"] == 1.0) and np.all(solid["mean_opacity"] == 1.0)
  haze = solidity.solidity(np.full(shown.shape, 0.3), shown)
  assert np.all(haze["iou"] == 0.0) and np.allclose(haze["mean_opacity"], 0.3)
  # Opaque everywhere: IoU is the silhouette's share of the frame.
  everywhere = solidity.solidity(np.ones(shown.shape), shown)
  assert np.allclose(everywhere["iou"], shown[0].mean())


def test_views_without_the_silhouette_are_left_out():
  shown = disc_silhouettes()
  shown[0] = False
  result = solidity.solidity(np.ones(shown.shape), shown)
  assert np.isnan(result["iou"][0]) and np.isnan(result["mean_opacity"][0])
  assert solidity.summarize(result["mean_opacity"])["count"] == VIEWS - 1


@pytest.mark.parametrize("threshold", [0.0, 1.0, -1.0])
def test_a_threshold_outside_the_open_unit_interval_is_refused(threshold):
  with pytest.raises(InputError, match="threshold"):
    solidity.solidity(np.ones((1, 2, 2)), np.ones((1, 2, 2), bool), threshold)


def test_bootstrap_intervals_separate_what_differs_and_not_what_does_not():
  high = solidity.summarize(RNG.normal(0.9, 0.05, 20))
  low = solidity.summarize(RNG.normal(0.5, 0.05, 20))
  same = solidity.summarize(RNG.normal(0.9, 0.05, 20))
  assert high["interval"][0] <= high["mean"] <= high["interval"][1]
  assert solidity.compare(high, low) == "higher" and solidity.compare(low, high) == "lower"
  assert solidity.compare(high, same) == "overlapping"
  assert solidity.compare(high, {"mean": None, "interval": None}) == "overlapping"


def test_the_bootstrap_is_deterministic_and_a_single_value_has_a_zero_width_interval():
  values = RNG.uniform(size=10)
  assert solidity.bootstrap_interval(values, seed=3) == solidity.bootstrap_interval(values, seed=3)
  assert solidity.bootstrap_interval([0.4]) == (0.4, 0.4)
  with pytest.raises(InputError, match="no values"):
    solidity.bootstrap_interval([np.nan, np.nan])


def test_the_relative_change_interval_covers_the_pooled_change():
  original = RNG.integers(20, 40, 15).astype(float)
  edited = np.round(original * 0.3)  # 70% fewer correspondences in every pair.
  low, high = solidity.relative_change_interval(edited, original)
  pooled = edited.sum() / original.sum() - 1
  assert low <= pooled <= high and high - low < 0.05
  unchanged_low, unchanged_high = solidity.relative_change_interval(original, original)
  assert unchanged_low == unchanged_high == 0.0


@pytest.mark.parametrize("difference, significant", [
    ([0.1, 0.1, 0.1, 0.1], True),
    ([-0.2, -0.1, -0.15, -0.12], True),
    ([0.1, -0.1, 0.05, -0.05], False),
])
def test_paired_difference_is_significant_only_when_its_interval_leaves_out_zero(difference,
                                                                                 significant):
  subtrahend = np.full(len(difference), 0.5)
  result = solidity.paired_difference(subtrahend + np.asarray(difference), subtrahend)
  assert result["mean"] == pytest.approx(np.mean(difference))
  assert result["interval"][0] <= result["mean"] <= result["interval"][1]
  assert result["significant"] == significant and result["count"] == len(difference)


def test_pairing_separates_a_consistent_difference_that_view_spread_hides():
  """Two edits, the first better by 0.02 at every view, views spread over 0.3: their own
  intervals overlap, the view-by-view difference's leaves out zero."""
  second = np.random.default_rng(1).uniform(0.6, 0.9, 12)
  first = second + 0.02
  assert solidity.compare(solidity.summarize(first), solidity.summarize(second)) == "overlapping"
  paired = solidity.paired_difference(first, second)
  assert paired["significant"] and paired["interval"][0] > 0


def test_paired_difference_leaves_out_views_either_did_not_measure():
  result = solidity.paired_difference([0.9, None, 0.8, np.nan], [0.7, 0.5, None, 0.6])
  assert result["count"] == 1 and result["mean"] == pytest.approx(0.2)
  with pytest.raises(InputError, match="same views"):
    solidity.paired_difference([0.9, 0.8], [0.7])
  unmeasured = solidity.paired_difference([None, 0.8], [0.5, None])
  assert unmeasured["count"] == 0 and not unmeasured["significant"]
