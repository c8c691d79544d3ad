"""A tiny analytic scene with exact ground truth: a sphere coloured by its normal, white
background, bounded box [-1, 1]^3, cameras on a ring around it."""

from __future__ import annotations

import numpy as np

from signerf_jax import camera
from signerf_jax.data.dataset import Dataset

SPHERE_RADIUS = 0.5


def sphere_dataset(num_views: int = 16, size: int = 24, distance: float = 2.5) -> Dataset:
  angles = np.linspace(0, 2 * np.pi, num_views, endpoint=False)
  heights = 0.8 * np.sin(3 * angles)
  eyes = np.stack([distance * np.cos(angles), distance * np.sin(angles), heights], -1)
  camera_to_world = np.asarray(camera.look_at(eyes.astype(np.float32), np.zeros(3, np.float32)))
  cameras = camera.Cameras.create(camera_to_world, fx=size * 1.2, width=size, height=size)
  images, depths = [], []
  for index in range(num_views):
    rays = camera.image_rays(cameras, index)
    origins, directions = np.asarray(rays.origins), np.asarray(rays.directions)
    # |o + t d|^2 = r^2 with |d| = 1.
    half_b = np.sum(origins * directions, -1)
    discriminant = half_b**2 - (np.sum(origins**2, -1) - SPHERE_RADIUS**2)
    hit = discriminant > 0
    t = -half_b - np.sqrt(np.maximum(discriminant, 0))
    normals = (origins + t[..., None] * directions) / SPHERE_RADIUS
    colour = np.clip(0.5 + 0.45 * normals, 0, 1)
    images.append(np.where(hit[..., None], colour, 1.0))
    depths.append(np.where(hit, t * np.asarray(rays.cos_to_optical_axis), 0.0))
  return Dataset(
      images=np.asarray(images, np.float32),
      cameras=cameras,
      image_names=tuple(f"view_{index:03d}.png" for index in range(num_views)),
      scene_bounds=np.array([[-1, -1, -1], [1, 1, 1]], np.float32),
      scene_kind="bounded",
      near=0.5,
      far=5.0,
      background_color=np.ones(3, np.float32),
      depths=np.asarray(depths, np.float32),
  )
