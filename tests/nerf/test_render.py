"""Written renders: the depth files hold the median depth, and the depth picture is finite and
ordered for any depth map."""

import numpy as np
import pytest

from signerf_jax import files
from signerf_jax.nerf import render


def test_write_renders_saves_median_depth_not_expected_depth(tmp_path):
  # An unbounded scene's expected depth is pulled far away by the last interval's weight; the
  # median stays on the surface. The files must hold the median.
  median = np.full((1, 4, 5), 2.0, np.float32)
  outputs = {"rgb": np.zeros((1, 4, 5, 3), np.float32),
             "accumulation": np.ones((1, 4, 5), np.float32),
             "depth": np.full((1, 4, 5), 40.0, np.float32),
             "median_depth": median}
  render.write_renders(tmp_path, ["./test/0001"], outputs)
  np.testing.assert_array_equal(files.read_exr(tmp_path / "test_0001.depth.exr"), median[0])
  assert (tmp_path / "test_0001.depth.png").is_file()
  assert (tmp_path / "test_0001.accumulation.png").is_file()


@pytest.mark.parametrize("depth", [
    np.full((3, 4), 1.5),                       # constant: an empty percentile range
    np.zeros((3, 4)),                           # zero depth
    np.linspace(1e-3, 1e3, 12).reshape(3, 4),   # six decades
])
def test_depth_image_is_finite_for_degenerate_depths(depth):
  picture = render.depth_image(depth)
  assert picture.shape == (3, 4, 3)
  assert np.all(np.isfinite(picture)) and picture.min() >= 0 and picture.max() <= 1


def test_depth_image_puts_near_and_far_at_opposite_ends_of_the_colour_map():
  depth = np.array([[1.0, 100.0]])
  picture = render.depth_image(depth, near=1.0, far=100.0)
  # Turbo runs from blue (near) to red (far).
  assert picture[0, 0, 2] > picture[0, 0, 0]
  assert picture[0, 1, 0] > picture[0, 1, 2]
