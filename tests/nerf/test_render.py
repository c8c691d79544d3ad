"""Rendering: marching only through the occupied cells' box renders as the whole march; a subset
of pixels renders as those pixels of the whole images; a supersampled pixel is the mean of the rays
through a grid inside it; written renders hold the median depth, and the depth picture is finite
and ordered for any depth map."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from signerf_jax import camera, files
from signerf_jax.errors import InputError
from signerf_jax.nerf import model as nerf_model
from signerf_jax.nerf import ray_samples, render

from small_nerf import count_compilations, small_model


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


def _rays(origins, directions) -> camera.Rays:
  directions = np.asarray(directions, np.float32)
  directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
  count = len(directions)
  return camera.Rays(np.asarray(origins, np.float32), directions,
                     np.ones(count, np.float32), np.zeros(count, np.int32))


@pytest.mark.parametrize("occupied_cells", ["off_centre_block", "block_and_speck", "everything",
                                            "nothing"])
def test_marching_only_through_the_occupied_box_renders_as_the_whole_march(sphere,
                                                                           occupied_cells):
  """Rendering marches only the steps through the box around the occupied cells, and gives the
  whole march's images (without the specks outside the box): camera rays, a ray starting inside
  the box, rays grazing its faces or parallel to an axis, and rays that miss the scene."""
  model = small_model(sphere)
  model = dataclasses.replace(model, capacity=dataclasses.replace(model.capacity,
                                                                   march_steps=192))
  variables = nerf_model.init_variables(model, jax.random.PRNGKey(0))
  resolution = variables["occupancy"].shape[0]
  # An off-centre block of cells, and its corners in scene units (the bounds are [-1, 1]^3).
  first, end = [(np.array(fractions) * resolution).astype(int)
                for fractions in ((0.55, 0.1, 0.3), (0.9, 0.4, 0.7))]
  low, high = first / resolution * 2 - 1, end / resolution * 2 - 1
  grid = np.zeros((resolution,) * 3, np.float32)
  if occupied_cells == "everything":
    grid[:] = 100.0
  elif occupied_cells != "nothing":
    grid[first[0]:end[0], first[1]:end[1], first[2]:end[2]] = 100.0
  with_specks = grid.copy()
  if occupied_cells == "block_and_speck":
    with_specks[2, 30, 30] = 2.0  # Alpha 0.06 across the cell.
  march = ray_samples.render_march(model, {**variables, "occupancy": jnp.asarray(with_specks)})
  if occupied_cells == "everything":
    assert march is None  # Nothing to skip: the whole march.
    return
  assert march.steps < model.capacity.march_steps / 2
  # A ray along the block's diagonal crosses the most cells; one starts inside it (past the
  # near plane, 0.5); one grazes its y face; one runs along an axis; two miss.
  hard_rays = _rays([low - (high - low), low - 0.2 * (high - low), [-3, low[1], 0],
                     [0.4, -3, 0], [-3, 4, 0], [5, 5, 5]],
                    [high - low, high - low, [1, 0, 0], [0, 1, 0], [1, 0, 0], [1, 1, 1]])
  rays = jax.tree.map(lambda *parts: jnp.concatenate(parts), hard_rays, *(
      jax.tree.map(lambda a: np.asarray(a).reshape((-1,) + np.asarray(a).shape[2:]),
                   camera.image_rays(sphere.cameras, index)) for index in (0, 5)))
  render_with = jax.jit(lambda grid, box, steps: nerf_model.render_rays(
      model, {**variables, "occupancy": grid}, rays, jax.random.PRNGKey(0), training=False,
      occupied_march=None if steps is None else ray_samples.OccupiedMarch(box, steps))[0],
                        static_argnums=2)
  whole = render_with(jnp.asarray(grid), None, None)
  occupied_only = render_with(jnp.asarray(with_specks), *march)
  for name in ("rgb", "accumulation", "depth", "distance", "median_depth"):
    np.testing.assert_allclose(occupied_only[name], whole[name], atol=1e-5, err_msg=name)
  if occupied_cells != "nothing":
    assert np.sum(np.asarray(whole["accumulation"]) > 0.1) > 20  # The block is seen.
  # Whole images march the short way too, and other views reuse the compilation.
  variables = {**variables, "occupancy": jnp.asarray(with_specks)}
  chunked = render.render_cameras(model, variables, sphere.cameras.take([0, 5]), 256)
  np.testing.assert_allclose(chunked["rgb"].reshape(-1, 3),
                             whole["rgb"][len(hard_rays.camera_indices):], atol=1e-5)
  with count_compilations() as compiled:
    render.render_cameras(model, variables, sphere.cameras.take([1, 2]), 256)
  assert not compiled


@pytest.mark.parametrize("pixels", ["off_centre_patch", "one_view_empty", "single_pixel",
                                    "everything", "nothing"])
def test_rendering_some_pixels_gives_those_pixels_of_the_whole_render_and_zeros_elsewhere(
    sphere, pixels):
  model = small_model(sphere)
  variables = nerf_model.init_variables(model, jax.random.PRNGKey(0))
  cameras = sphere.cameras.take([0, 3, 5])
  chosen = np.zeros((3, cameras.height, cameras.width), bool)
  if pixels == "off_centre_patch":
    chosen[:, 1:5, -6:-1] = True
  elif pixels == "one_view_empty":
    chosen[0, ::3, ::2] = chosen[2, -3:] = True
  elif pixels == "single_pixel":
    chosen[1, -1, 0] = True
  elif pixels == "everything":
    chosen[:] = True
  whole = render.render_cameras(model, variables, cameras, 256)
  some = render.render_cameras(model, variables, cameras, 256, pixels=chosen)
  assert set(some) == set(whole)
  for name, image in some.items():
    assert image.shape == whole[name].shape and image.dtype == np.float32, name
    np.testing.assert_allclose(image[chosen], whole[name][chosen], atol=1e-6, err_msg=name)
    assert not np.any(image[~chosen]), name
  with pytest.raises(InputError, match="pixels"):
    render.render_cameras(model, variables, cameras, 256, pixels=chosen[:2])


@pytest.mark.parametrize("supersampling", [1, 2, 3])
@pytest.mark.parametrize("pixels", ["every_pixel", "off_centre_patch"])
def test_a_supersampled_pixel_is_the_mean_of_the_rays_through_a_grid_inside_it(
    sphere, supersampling, pixels):
  """supersampling N renders each pixel as the mean of the N x N rays through the centres of an
  N x N grid of sub-pixels (1: the pixel's centre ray), for every output, also when only some
  pixels are rendered; other supersamplings reuse the compilation."""
  model = small_model(sphere)
  variables = nerf_model.init_variables(model, jax.random.PRNGKey(0))
  cameras = sphere.cameras.take([0, 5])
  chosen = np.ones((2, cameras.height, cameras.width), bool)
  if pixels == "off_centre_patch":
    chosen[:] = False
    chosen[1, 2:7, -5:] = True
  rendered = render.render_cameras(model, variables, cameras, 256, pixels=chosen,
                                   supersampling=supersampling)
  rows, columns = np.meshgrid(np.arange(cameras.height), np.arange(cameras.width), indexing="ij")
  expected = {name: np.zeros_like(image) for name, image in rendered.items()}
  for y in range(supersampling):
    for x in range(supersampling):
      for view in range(2):  # Rays through sub-pixel centres, built independently of render.
        rays = camera.pixel_rays(cameras, np.full(rows.shape, view),
                                 columns + (x + 0.5) / supersampling,
                                 rows + (y + 0.5) / supersampling)
        for name, image in render.render_rays_chunked(model, variables, rays, 256).items():
          expected[name][view] += image / supersampling**2
  for name, image in rendered.items():
    np.testing.assert_allclose(image[chosen], expected[name][chosen], atol=1e-5, err_msg=name)
    assert not np.any(image[~chosen]), name
  centre = render.render_cameras(model, variables, cameras, 256, pixels=chosen)
  difference = np.abs(rendered["rgb"] - centre["rgb"]).max()
  assert (difference == 0) == (supersampling == 1)  # The sub-pixel rays see other colours.
  with count_compilations() as compiled:
    render.render_cameras(model, variables, cameras, 256, pixels=chosen, supersampling=4)
  assert not compiled


@pytest.mark.parametrize("supersampling", [0, -2, 1.5, True, "2"])
def test_supersampling_must_be_a_positive_integer(sphere, supersampling):
  model = small_model(sphere)
  variables = nerf_model.init_variables(model, jax.random.PRNGKey(0))
  with pytest.raises(InputError, match="supersampling"):
    render.render_cameras(model, variables, sphere.cameras.take([0]), 256,
                          supersampling=supersampling)
