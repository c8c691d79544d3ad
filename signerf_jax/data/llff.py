"""LLFF forward-facing captures: `poses_bounds.npy` with `images/` and downscaled `images_N/`.

Each row of poses_bounds.npy is a flattened 3x5 matrix [R | t | hwf] followed by the near and far
z-depth bounds of that view's content (from its COLMAP points). R's columns are LLFF's camera
axes [down, right, backwards]; hwf is (height, width, focal) at full resolution. The images of
a folder, in sorted file-name order, belong to the rows in order.

Normalisation: as LLFF's `recenter_poses`, the average pose becomes the identity (the cameras
look down -z, y up); then the box around every view's frustum between its near and far bounds
is centred and scaled onto [-1, 1]^3.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from signerf_jax.camera import Cameras
from signerf_jax.data import poses as poses_lib
from signerf_jax.data import views
from signerf_jax.data.dataset import Dataset
from signerf_jax.errors import InputError

POSES_NAME = "poses_bounds.npy"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def read_llff(root: str | os.PathLike, *, split: str = "train", downscale: int = 1,
              eval_every: int = 8) -> Dataset:
  """Reads an LLFF capture into a normalised "forward_facing" Dataset.

  Args:
    root: the directory holding poses_bounds.npy.
    split: "train", "eval" (every `eval_every`-th view, as NeRF's `llffhold`) or "all".
    downscale: image downscale relative to the full resolution in hwf. `images_{downscale}/` is
      used when present, otherwise the closest finer `images_M/` (M divides downscale) is
      area-resampled.
  """
  root = Path(root)
  path = root / POSES_NAME
  if not path.is_file():
    raise InputError("file not found", path)
  try:
    rows = np.load(path, allow_pickle=False)
  except (ValueError, OSError, EOFError) as error:
    raise InputError(f"not a readable .npy array ({error})", path) from None
  if rows.ndim != 2 or rows.shape[1] != 17 or rows.shape[0] == 0:
    raise InputError(f"must be an [N, 17] array, got shape {rows.shape}", path)
  matrices = rows[:, :15].reshape(-1, 3, 5).astype(np.float64)
  bounds = rows[:, 15:].astype(np.float64)
  height, width = matrices[0, :2, 4]
  if not (np.all(np.isfinite([width, height])) and min(width, height) >= 1
          and width == int(width) and height == int(height)):
    raise InputError(f"hwf image size must be positive whole pixels, got {width}x{height}",
                     path, "poses_bounds[0].hwf")
  camera_to_world, focals = [], []
  for index, matrix in enumerate(matrices):
    field = f"poses_bounds[{index}]"
    if not np.array_equal(matrix[:2, 4], [height, width]):
      raise InputError(f"hwf size {matrix[:2, 4].tolist()} differs from the first row's "
                       f"{[height, width]} (images of mixed sizes)", path, f"{field}.hwf")
    focals.append(poses_lib.check_focal_length(matrix[2, 4], path, f"{field}.focal"))
    camera_to_world.append(poses_lib.check_camera_to_world(
        poses_lib.llff_to_opengl(matrix[:, :4]), path, f"{field}.pose"))
    near, far = bounds[index]
    if not (np.isfinite(near) and np.isfinite(far) and 0 < near < far):
      raise InputError(f"near/far bounds must satisfy 0 < near < far, got {near}, {far}",
                       path, f"{field}.bounds")
  camera_to_world, focals = np.stack(camera_to_world), np.asarray(focals)
  # Half the field of view as normalised image coordinates (x, y) of the image corner.
  corner = np.array([width / 2, height / 2]) / focals[:, None]
  frustum_points = _frustum_corners(camera_to_world, corner, bounds).reshape(-1, 3)
  world_from_source = _normalisation(camera_to_world, frustum_points)
  scene_points = poses_lib.transform_points(world_from_source, frustum_points)
  scale = poses_lib.similarity_scale(world_from_source)
  near = scale * np.min(bounds[:, 0])
  # The bounds are z-depths: the ray through an image corner travels 1/cos further.
  far = scale * np.max(bounds[:, 1] * np.sqrt(1 + np.sum(corner**2, -1)))

  folder, folder_factor = _image_folder(root, downscale)
  image_paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
  if len(image_paths) != len(rows):
    raise InputError(f"holds {len(image_paths)} images but {POSES_NAME} has {len(rows)} rows",
                     folder)
  selected = views.split_indices(len(rows), split, eval_every)
  cameras = Cameras.create(camera_to_world, fx=focals, width=int(width), height=int(height))
  cameras = poses_lib.transform_cameras(world_from_source, cameras)
  cameras = cameras.take(selected).downscaled(downscale)
  folder_size = (round(width / folder_factor), round(height / folder_factor))
  images = np.stack([
      views.read_view(lambda p: views.read_color(p, (0.0, 0.0, 0.0)), image_paths[index],
                      f"image for {POSES_NAME} row {index}", file_size=folder_size,
                      target_size=(cameras.width, cameras.height), method="area",
                      size_tolerance=1)
      for index in selected])
  return Dataset(
      images=images, cameras=cameras,
      image_names=tuple(image_paths[index].relative_to(root).as_posix() for index in selected),
      scene_bounds=np.stack([scene_points.min(0), scene_points.max(0)]).astype(np.float32),
      scene_kind="forward_facing", near=float(near), far=float(far),
      world_from_source=world_from_source.astype(np.float32), root=str(root))


def _frustum_corners(camera_to_world: np.ndarray, corner: np.ndarray,
                     bounds: np.ndarray) -> np.ndarray:
  """[N, 8, 3] world corners of each view's frustum between its near and far z-depths.

  Args:
    camera_to_world: [N, 3, 4] OpenGL poses.
    corner: [N, 2] normalised (x, y) of the image corner.
    bounds: [N, 2] near and far z-depths.
  """
  signs = np.array([[-1, -1], [-1, 1], [1, -1], [1, 1]], np.float64)
  xy = corner[:, None, :] * signs  # [N, 4, 2]
  # A point at z-depth d along normalised (x, y) is d * (x, y, -1) in OpenGL camera space.
  directions = np.concatenate([xy, -np.ones_like(xy[..., :1])], -1)
  local = bounds[:, :, None, None] * directions[:, None]  # [N, 2, 4, 3]
  world = np.einsum("nij,nabj->nabi", camera_to_world[:, :, :3], local)
  return (world + camera_to_world[:, None, None, :, 3]).reshape(-1, 8, 3)


def _normalisation(camera_to_world: np.ndarray, content_points: np.ndarray) -> np.ndarray:
  """Recentres on the average pose (LLFF's poses_avg), then fits the content into [-1, 1]^3."""
  centre = camera_to_world[:, :, 3].mean(0)
  back = camera_to_world[:, :, 2].sum(0)
  back /= np.linalg.norm(back)
  right = np.cross(camera_to_world[:, :, 1].sum(0), back)
  right /= np.linalg.norm(right)
  average_rotation = np.stack([right, np.cross(back, right), back], -1)
  average_from_source = poses_lib.similarity(1.0, average_rotation.T,
                                             -average_rotation.T @ centre)
  points = poses_lib.transform_points(average_from_source, content_points)
  return poses_lib.unit_box_similarity(points.min(0), points.max(0)) @ average_from_source


def _image_folder(root: Path, downscale: int) -> tuple[Path, int]:
  """The folder to read images from and its downscale factor relative to full resolution.

  `images_{downscale}` (or `images` for 1) when present; otherwise the coarsest folder whose
  factor divides `downscale`, to be area-resampled the rest of the way.
  """
  factors = {}
  for folder in root.iterdir():
    match = re.fullmatch(r"images(?:_(\d+))?", folder.name)
    if folder.is_dir() and match:
      factors[int(match.group(1) or 1)] = folder
  usable = [factor for factor in factors if downscale % factor == 0]
  if not usable:
    raise InputError(f"no image folder for downscale {downscale}: found "
                     f"{sorted(f.name for f in factors.values()) or 'none'}; pass a downscale "
                     "that one of them divides", root, "downscale")
  factor = max(usable)
  return factors[factor], factor
