"""Images of an edited NeRF rendered only where the edit can show.

A NeRF with an edit region (`nerf.model`) renders every ray that misses the region exactly as
the frozen original does. So its image at a camera is the original's image with only the pixels
whose rays cross the region rendered again: at an edit's held-out cameras and along its orbit
video the region covers a small share of the pixels, and the edited images cost that share of a
full render once the original's are there.
"""

from __future__ import annotations

import numpy as np

from signerf_jax import camera
from signerf_jax.nerf import model as nerf_model
from signerf_jax.nerf import render


def region_pixels(model: nerf_model.NerfModel, cameras: camera.Cameras,
                  supersampling: int | None = None) -> np.ndarray:
  """[N, H, W] bool: the pixels of `cameras` where `model` (with an edit region) can differ from
  its original, i.e. where one of the pixel's rays crosses the region (supersampling^2 rays a
  pixel, as `render.render_cameras` renders them; None: the model's `pixel_samples`)."""
  if supersampling is None:
    supersampling = model.capacity.pixel_samples
  pixels = np.zeros((cameras.num_cameras, cameras.height, cameras.width), bool)
  for position in camera.subpixel_positions(supersampling):
    for index in range(cameras.num_cameras):
      rays = render.image_rays(cameras, index, position)
      pixels[index] |= render.crossing_rays(model, rays.reshape(-1)).reshape(rays.shape)
  return pixels


def render_over_original(model: nerf_model.NerfModel, variables, cameras: camera.Cameras,
                         original_rgb: np.ndarray) -> np.ndarray:
  """The edited NeRF's colour at `cameras`: [N, H, W, 3] float32 in [0, 1].

  Args:
    model, variables: the edited NeRF; with an edit region only the pixels whose rays cross it
      are rendered, the others taken from `original_rgb`; without one, every pixel.
    original_rgb: [N, H, W, 3] the original NeRF's renders at `cameras` (`render.render_cameras`
      with its default supersampling).
  """
  if model.edit_region is None:
    return render.render_cameras(model, variables, cameras)["rgb"]
  pixels = region_pixels(model, cameras)
  rendered = render.render_cameras(model, variables, cameras, pixels=pixels)["rgb"]
  return np.where(pixels[..., None], rendered, np.asarray(original_rgb, np.float32))
