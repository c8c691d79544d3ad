import cv2
import numpy as np
import pytest

from signerf_jax.errors import InputError
from signerf_jax.geometry import masks


def random_masks(seed, shape=(2, 40, 56), density=0.01):
  return np.random.default_rng(seed).random(shape) < density


@pytest.mark.parametrize("seed, density", [(0, 0.003), (1, 0.02), (2, 0.3)])
def test_distance_to_mask_matches_opencv(seed, density):
  mask = random_masks(seed, density=density)
  mask[0, 0, 0] = mask[1, -1, -1] = True  # corners: the row pass's boundaries
  distance = np.asarray(masks.distance_to_mask(mask, 12))
  for index in range(len(mask)):
    expected = cv2.distanceTransform((~mask[index]).astype(np.uint8), cv2.DIST_L2,
                                     cv2.DIST_MASK_PRECISE)
    np.testing.assert_allclose(distance[index], np.minimum(expected, 13), atol=1e-4)


def test_empty_mask_is_far_everywhere():
  distance = masks.distance_to_mask(np.zeros((8, 9), bool), 3)
  np.testing.assert_array_equal(distance, 4.0)


@pytest.mark.parametrize("size", [128, 256])
def test_dilation_is_a_disc_scaled_with_resolution(size):
  mask = np.zeros((1, size, size), bool)
  mask[0, size // 2, size // 2] = True
  radius_at_reference = 40.0  # at 512: 10 px at 128, 20 px at 256
  dilated = np.asarray(masks.dilate_and_feather(mask, radius=radius_at_reference))
  radius = radius_at_reference * size / 512
  rows, columns = np.mgrid[:size, :size]
  disc = (rows - size // 2)**2 + (columns - size // 2)**2 <= radius**2
  np.testing.assert_array_equal(dilated[0], disc)


def test_feathering_ramps_linearly_outside_the_dilated_mask():
  mask = np.zeros((64, 64), bool)
  mask[:, :20] = True
  soft = np.asarray(masks.dilate_and_feather(mask, radius=32.0, feather=64.0))  # 4 and 8 px
  row = soft[30]
  np.testing.assert_array_equal(row[:24], 1.0)  # mask plus 4 px of dilation
  np.testing.assert_allclose(row[24:32], 1.0 - np.arange(1, 9) / 8, atol=1e-6)
  np.testing.assert_array_equal(row[32:], 0.0)


def test_no_dilation_returns_the_mask_and_negative_radius_is_an_error():
  mask = random_masks(3)
  np.testing.assert_array_equal(masks.dilate_and_feather(mask), mask.astype(np.float32))
  with pytest.raises(InputError, match="radius"):
    masks.dilate_and_feather(mask, radius=-1.0)


def test_dilation_does_not_recompile_for_new_masks():
  masks.dilate_and_feather(random_masks(4), radius=16.0).block_until_ready()
  size = masks.dilate_and_feather._cache_size()
  masks.dilate_and_feather(random_masks(5), radius=16.0).block_until_ready()
  assert masks.dilate_and_feather._cache_size() == size


def test_views_with_empty_masks_are_reported():
  view_masks = np.zeros((4, 8, 8, 1), np.float32)
  view_masks[1, 2, 2] = 1.0
  view_masks[3, :2, :2] = 0.5
  np.testing.assert_array_equal(masks.views_with_empty_masks(view_masks), [0, 2])
  np.testing.assert_array_equal(masks.views_with_empty_masks(view_masks, min_pixels=2), [0, 1, 2])
  with pytest.raises(InputError, match="not visible in any of the 4 views"):
    masks.views_with_empty_masks(np.zeros((4, 8, 8)))
