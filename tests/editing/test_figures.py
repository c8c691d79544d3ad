"""Figure helpers (`editing.figures`)."""

import numpy as np
import pytest

from signerf_jax.editing import figures


@pytest.mark.parametrize("top, left", [(2, 3), (0, 0)])  # inside; touching the image's corner
def test_outline_draws_the_masks_boundary_and_keeps_everything_else(top, left):
  image = np.full((10, 12), 0.5, np.float32)
  mask = np.zeros((10, 12), bool)
  mask[top:top + 4, left:left + 5] = True
  outlined = figures.outline(image, mask, color=(1.0, 0.0, 0.0))
  boundary = mask.copy()
  boundary[top + 1:top + 3, left + 1:left + 4] = False
  np.testing.assert_array_equal(np.all(outlined == [1.0, 0.0, 0.0], axis=-1), boundary)
  np.testing.assert_array_equal(outlined[~boundary], 0.5)
  assert outlined.shape == (10, 12, 3)


def test_outline_of_an_empty_mask_is_the_image():
  image = np.random.default_rng(0).random((6, 7, 3)).astype(np.float32)
  np.testing.assert_array_equal(figures.outline(image, np.zeros((6, 7), bool)), image)
