"""Rendering: marching only through the occupied cells' box renders as the whole march; a subset
of pixels renders as those pixels of the whole images; a supersampled pixel is the mean of the rays
through a grid inside it; written renders hold the median depth, and the depth picture is finite
and ordered for any depth map; a chunk never holds more rays than there are (beyond the default
chunk), and a chunk size whose buffers cannot fit in memory is refused before any work."""

import dataclasses
import subprocess
import sys
import time

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


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.parametrize("count,chunk_size,chunks", [
    (300, 10**13, [4096]),        # Padded to the default chunk only: its compilation serves.
    (5000, 10**13, [5000]),       # No more than the rays.
    (5000, 2048, [2048] * 3),
    (300, 256, [256, 256]),
])
def test_a_chunk_holds_no_more_than_the_rays_or_the_default_chunk(sphere, monkeypatch, count,
                                                                  chunk_size, chunks):
  model = small_model(sphere)
  variables = nerf_model.init_variables(model, jax.random.PRNGKey(0))
  shapes = []

  def fake_render_chunk(model, variables, chunk, *args):
    shapes.append(len(chunk.camera_indices))
    return {name: np.zeros((len(chunk.camera_indices),) + ((3,) if name == "rgb" else ()),
                           np.float32) for name in render.IMAGE_OUTPUTS}

  monkeypatch.setattr(render, "_render_chunk", fake_render_chunk)
  rays = _rays(np.zeros((count, 3)), np.tile([[0.0, 0.0, 1.0]], (count, 1)))
  outputs = render.render_rays_chunked(model, variables, rays, chunk_size)
  assert shapes == chunks
  assert outputs["rgb"].shape == (count, 3)


@pytest.mark.slow
def test_a_huge_chunk_size_renders_as_the_default_one(sphere):
  model = small_model(sphere)
  variables = nerf_model.init_variables(model, jax.random.PRNGKey(0))
  cameras = sphere.cameras.take([0, 5])
  default = render.render_cameras(model, variables, cameras)
  with count_compilations() as compiled:
    huge = render.render_cameras(model, variables, cameras, 10**13)
  assert not compiled
  for name, image in huge.items():
    np.testing.assert_array_equal(image, default[name], err_msg=name)


@pytest.mark.parametrize("chunk_size", [0, -5, 2.5, True])
def test_a_chunk_size_must_be_a_positive_integer(sphere, chunk_size):
  model = small_model(sphere)
  variables = nerf_model.init_variables(model, jax.random.PRNGKey(0))
  with pytest.raises(InputError, match="chunk_size: must be a positive integer"):
    render.render_cameras(model, variables, sphere.cameras.take([0]), chunk_size)
  with pytest.raises(InputError, match="chunk_size: must be a positive integer"):
    render.check_chunk_size(chunk_size)


def test_a_chunk_size_whose_buffers_cannot_fit_in_memory_is_refused():
  gib = 2**30
  render.check_chunk_size(4096, "--chunk_size", memory=16 * gib)
  render.check_chunk_size(16 * gib // render.CHUNK_BYTES_PER_RAY, memory=16 * gib)
  with pytest.raises(InputError) as error:
    render.check_chunk_size(10**13, "--chunk_size", memory=16 * gib)
  assert error.value.field == "--chunk_size"
  assert str(error.value) == (
      "--chunk_size: 10000000000000 rays at once need at least 1.2 PiB of memory (136 bytes a "
      "ray for the rays and their outputs alone), more than this machine's 16.0 GiB; the "
      "default is 4096")
  with pytest.raises(InputError, match="more than this machine's"):
    render.check_chunk_size(16 * gib // render.CHUNK_BYTES_PER_RAY + 1, memory=16 * gib)
  # What the machine has, by default.
  with pytest.raises(InputError, match="more than this machine's"):
    render.check_chunk_size(render.physical_memory() // render.CHUNK_BYTES_PER_RAY + 1)


@pytest.mark.slow
@pytest.mark.parametrize("command", [["eval"], ["render"]])
def test_the_commands_refuse_a_huge_chunk_size_before_loading_anything(command, tmp_path):
  # A missing run: the chunk size is refused first, in seconds, without allocating its buffers
  # (numpy failed on "Unable to allocate 109. TiB" after loading the run and the data).
  started = time.monotonic()
  process = subprocess.run(
      [sys.executable, "-m", "signerf_jax.cli", *command, "--run", str(tmp_path / "missing"),
       "--chunk_size", "10000000000000"], capture_output=True, text=True, timeout=120)
  assert process.returncode == 2, process.stderr
  assert process.stderr.startswith(f"signerf {command[0]}: error: --chunk_size: "
                                   "10000000000000 rays at once need at least 1.2 PiB of "
                                   "memory"), process.stderr
  assert "this machine's" in process.stderr and "Traceback" not in process.stderr
  assert time.monotonic() - started < 60


def test_image_rays_compile_once_per_image_size_whatever_the_number_of_cameras(sphere):
  cameras = sphere.cameras
  first = render.image_rays(cameras.take([0, 1, 2]), 2, (0.25, 0.75))
  expected = camera.image_rays(cameras, 2, (0.25, 0.75))
  for ours, theirs in zip(jax.tree.leaves(first), jax.tree.leaves(expected)):
    np.testing.assert_allclose(ours, theirs, atol=3e-7)  # float rounding of the gathers
  with count_compilations() as compiled:
    rays = render.image_rays(cameras, 9, np.array([0.5, 0.5], np.float32))
  assert not compiled
  np.testing.assert_array_equal(rays.camera_indices, 9)
