"""What a NeRF training step samples: the images on device (`TrainingData`), each step's batch
of rays and target colours (`step_batch`), and for a model with an edit region, the pixels whose
rays cross it (`RegionRays`).

A model with an edit region trains only on the pixels whose rays cross the region: elsewhere it
renders the frozen original exactly, so those pixels have no gradient, and spending the batch on
them would waste most of it (an object filling a tenth of the frames leaves nine tenths of a
uniform batch idle). The original's render around the region is computed once for each of these
rays, so a step evaluates the trained field alone.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from signerf_jax import camera
from signerf_jax.data.dataset import Dataset
from signerf_jax.errors import InputError
from signerf_jax.nerf import keypoint_depth
from signerf_jax.nerf import model as nerf_model
from signerf_jax.nerf.capacity import Capacity


@struct.dataclass
class RegionRays:
  """The training pixels whose rays cross a model's edit region, with the frozen original's
  render around the region on each (`with_region_rays`).

  Attributes:
    pixels: [P] int32 flat indices into the images' [N, H, W].
    surroundings: `nerf_model.RegionSurroundings` of shape [P].
  """

  pixels: jax.Array
  surroundings: nerf_model.RegionSurroundings


@struct.dataclass
class TrainingData:
  """Training images on device (not donated; the same every step).

  Attributes:
    images: [N, H, W, 3] float32.
    cameras: N cameras.
    pixel_weights: [N, H, W] float32 per-pixel loss weights (1 = normal, 0 = ignore).
    alphas: None or [N, H, W] float32 opacity of RGBA images (`Dataset.alphas`).
    region: for a model with an edit region, the only pixels a step samples (`RegionRays`).
    keypoints: depths of triangulated keypoints (`keypoint_depth.KeypointDepths`), or None.
    neighbour_views: None or [N, K] int32 the views each view's samples are compared with
      (`photo_consistency.neighbour_views`).
  """

  images: jax.Array
  cameras: camera.Cameras
  pixel_weights: jax.Array
  alphas: jax.Array | None = None
  region: RegionRays | None = None
  keypoints: keypoint_depth.KeypointDepths | None = None
  neighbour_views: jax.Array | None = None

  @classmethod
  def from_dataset(cls, dataset: Dataset, pixel_weights=None) -> "TrainingData":
    weights = np.ones(dataset.images.shape[:3], np.float32)
    if dataset.masks is not None:
      weights = weights * dataset.masks
    if pixel_weights is not None:
      pixel_weights = np.asarray(pixel_weights, np.float32)
      if pixel_weights.shape != weights.shape:
        raise InputError(f"pixel weights have shape {pixel_weights.shape}, the images "
                         f"{weights.shape}", dataset.root or None, "pixel_weights")
      weights = weights * pixel_weights
    if dataset.masks is not None and not np.any(dataset.masks > 0):
      # Every pixel masked out: the loss would be 0 from the first step, training would fit
      # nothing and report a perfect score. (Zero pixel weights from a caller are a choice:
      # a fine-tune that leaves the field as it is.)
      raise InputError(f"every pixel of the {dataset.num_images} training views is masked out: "
                       "the masks leave nothing to train on", dataset.root or None, "masks")
    alphas = None if dataset.alphas is None else jnp.asarray(dataset.alphas, jnp.float32)
    return cls(jnp.asarray(dataset.images, jnp.float32),
               jax.tree.map(jnp.asarray, dataset.cameras), jnp.asarray(weights), alphas)


def _pixel_rays(cameras: camera.Cameras, image_shape: tuple[int, int, int], flat_pixels
                ) -> camera.Rays:
  """The rays through the centres of `flat_pixels` [C] (indices into [N, H, W])."""
  index, row, column = jnp.unravel_index(flat_pixels, image_shape)
  return camera.pixel_rays(cameras, index, column + 0.5, row + 0.5)


@functools.partial(jax.jit, static_argnums=(0, 2))
def _crossing_chunk(model, cameras, image_shape, flat_pixels):
  return nerf_model.crosses_region(model, _pixel_rays(cameras, image_shape, flat_pixels))


@functools.partial(jax.jit, static_argnums=(0, 3))
def _surroundings_chunk(model, variables, cameras, image_shape, flat_pixels):
  return nerf_model.region_surroundings(model, variables,
                                        _pixel_rays(cameras, image_shape, flat_pixels))


def _in_chunks(function, flat_pixels: np.ndarray, chunk_size: int):
  """`function(chunk)` over fixed-size chunks of `flat_pixels` [P] (the last one padded, so one
  compilation serves all), concatenated into numpy arrays [P, ...]."""
  outputs = []
  for start in range(0, len(flat_pixels), chunk_size):
    chunk = flat_pixels[start:start + chunk_size]
    result = function(np.pad(chunk, (0, chunk_size - len(chunk)), mode="edge"))
    outputs.append(jax.tree.map(lambda array: np.asarray(array)[:len(chunk)], result))
  return jax.tree.map(lambda *arrays: np.concatenate(arrays), *outputs)


def with_region_rays(data: TrainingData, model: nerf_model.NerfModel, variables,
                     chunk_size: int = 8192) -> TrainingData:
  """`data` with its `RegionRays` when `model` has an edit region (`variables` hold the
  original's): every pixel of non-zero weight whose ray crosses the region, with the original's
  render around the region (the only rays rendered: a box test finds them first)."""
  if model.edit_region is None or data.region is not None:
    return data
  image_shape = tuple(data.pixel_weights.shape)
  weighted = np.flatnonzero(np.asarray(data.pixel_weights).reshape(-1) > 0).astype(np.int32)
  crossing = (_in_chunks(functools.partial(_crossing_chunk, model, data.cameras, image_shape),
                         weighted, 16 * chunk_size) if len(weighted) else np.zeros(0, bool))
  pixels = weighted[crossing]
  if not len(pixels):
    raise InputError(f"no training pixel sees the edit region {model.edit_region}",
                     field="edit_region")
  surroundings = _in_chunks(functools.partial(_surroundings_chunk, model, variables,
                                              data.cameras, image_shape), pixels, chunk_size)
  return data.replace(region=RegionRays(jnp.asarray(pixels), jax.tree.map(jnp.asarray,
                                                                          surroundings)))


def sample_rays(key, data: TrainingData, batch_size: int):
  """A uniform random batch of training pixels' rays: over every pixel, or over the region's.

  Returns:
    rays: Rays [batch_size].
    pixels: (camera_index, row, column), each [batch_size] int32.
    surroundings: the region's `RegionSurroundings` [batch_size], or None.
  """
  if data.region is None:
    rays, pixels = camera.random_rays(key, data.cameras, batch_size)
    return rays, pixels, None
  choice = jax.random.randint(key, (batch_size,), 0, data.region.pixels.shape[0])
  pixels = jnp.unravel_index(data.region.pixels[choice], data.pixel_weights.shape)
  rays = camera.pixel_rays(data.cameras, pixels[0], pixels[2] + 0.5, pixels[1] + 0.5)
  return rays, pixels, jax.tree.map(lambda array: array[choice], data.region.surroundings)


def pixels_per_step(capacity: Capacity, per_side: int) -> int:
  """Pixels a training step samples with `per_side`^2 rays each: rays_per_batch / per_side^2,
  rounded down to a multiple of `Capacity.sample_groups` so that their rays split into the
  groups evenly (3 x 3 rays a pixel of 8,192 would be 910 pixels, 8,190 rays, which 8 groups do
  not split)."""
  groups = capacity.sample_groups
  return max(groups, capacity.rays_per_batch // per_side**2 // groups * groups)


def step_batch(model: nerf_model.NerfModel, data: TrainingData, ray_key, background_key):
  """A step's batch: `Capacity.pixel_samples`^2 rays through each of rays_per_batch / that many
  random pixels (one ray for an edit region: its surroundings are stored per pixel centre).

  Returns:
    rays [R], the pixels' target colours [P, 3] and weights [P], backgrounds (None or [R, 3]),
    the region's surroundings [R] (or None), and R / P.
  """
  per_side = model.capacity.pixel_samples if data.region is None else 1
  rays, (index, row, column), surroundings = sample_rays(
      ray_key, data, pixels_per_step(model.capacity, per_side))
  target = data.images[index, row, column]
  background = None
  if data.alphas is not None and model.background is not None:
    # instant-NGP's random backgrounds: where the photo is transparent the target takes a new
    # colour each step, so empty space must stay empty. With the constant background alone,
    # density of that colour in front of it would fit the photos equally well (floaters that
    # hide the object in other views: the sparse-view failure).
    background = jax.random.uniform(background_key, target.shape)
    transparency = (1.0 - data.alphas[index, row, column])[:, None]
    target = target + transparency * (background - model.background)
    background = jnp.repeat(background, per_side**2, axis=0)
  if per_side > 1:
    rays = camera.subpixel_rays(data.cameras, index, row, column, per_side)
  return (rays, target, data.pixel_weights[index, row, column], background, surroundings,
          per_side**2)


