"""Per-view files shared by every dataset format: colour, masks, depth, object ids, resampling."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from signerf_jax import files
from signerf_jax.errors import InputError


def read_color_and_alpha(path: str | os.PathLike, background_color) -> np.ndarray:
  """[H, W, 4] float32 in [0, 1]: the RGB image, RGBA composited on `background_color` ([3]),
  and its opacity (1 for images without alpha).

  The alpha is straight (not premultiplied), as Blender and nerfstudio write it.
  """
  image = files.read_image(path)
  if image.shape[-1] == 1:
    image = np.repeat(image, 3, axis=-1)
  if image.shape[-1] == 3:
    return np.concatenate([image, np.ones_like(image[..., :1])], axis=-1)
  alpha = image[..., 3:]
  background = np.asarray(background_color, np.float32)
  return np.concatenate([image[..., :3] * alpha + background * (1.0 - alpha), alpha], axis=-1)


def read_mask(path: str | os.PathLike) -> np.ndarray:
  """A validity mask [H, W] float32 in [0, 1] (nerfstudio: 0 = ignore the pixel)."""
  return files.read_image(path)[..., 0]


def read_depth(path: str | os.PathLike, png_unit_scale: float) -> np.ndarray:
  """A z-depth map [H, W] float32: an EXR as stored, or a 16-bit PNG times `png_unit_scale`."""
  if Path(path).suffix.lower() == ".exr":
    depth = files.read_exr(path)
    return depth[..., 0] if depth.ndim == 3 else depth
  raw = files.read_image(path)[..., 0] * np.float32(np.iinfo(np.uint16).max)
  return np.round(raw) * np.float32(png_unit_scale)


def read_object_ids(path: str | os.PathLike) -> np.ndarray:
  """An object-id map [H, W] int32 stored as an 8-bit grey PNG (0 = no object)."""
  return np.round(files.read_image(path)[..., 0] * 255).astype(np.int32)


def read_silhouette(path: str | os.PathLike) -> np.ndarray:
  """An object-id map [H, W] int32 from a black-and-white silhouette (NeuS/IDR masks, grey or
  RGB): id 1 where the first channel exceeds 0.5, else 0."""
  return (files.read_image(path)[..., 0] > 0.5).astype(np.int32)


def write_object_ids(path: str | os.PathLike, object_ids: np.ndarray) -> None:
  """Writes an [H, W] object-id map (ids 0..255) as an 8-bit grey PNG, exactly."""
  object_ids = np.asarray(object_ids)
  if object_ids.min(initial=0) < 0 or object_ids.max(initial=0) > 255:
    raise InputError("object ids must lie in 0..255 to fit an 8-bit PNG", path)
  files.write_image(path, object_ids.astype(np.float32) / 255.0)


def resize(array: np.ndarray, width: int, height: int, method: str) -> np.ndarray:
  """Resamples an [H, W] or [H, W, C] image to `width` x `height`.

  Args:
    method: "area" averages the source pixels each target pixel covers (colours, soft masks);
      "nearest" picks the source pixel under each target pixel's centre (depth, ids: averaging
      would invent depths between a foreground and its background, or ids that do not exist).
  """
  source_height, source_width = array.shape[:2]
  if (source_width, source_height) == (width, height):
    return array
  if method == "area":
    return cv2.resize(array, (width, height), interpolation=cv2.INTER_AREA)
  rows = ((np.arange(height) + 0.5) * source_height / height).astype(np.int64)
  columns = ((np.arange(width) + 0.5) * source_width / width).astype(np.int64)
  return array[rows[:, None], columns[None, :]]


def read_view(read: Callable[[Path], np.ndarray], path: str | os.PathLike, field: str, *,
              file_size: tuple[int, int], target_size: tuple[int, int], method: str,
              size_tolerance: int = 0, size_source: str = "the cameras") -> np.ndarray:
  """Reads one per-view file, checks its size and resamples it to the size the cameras use.

  Args:
    read: the reader for this kind of file (e.g. `read_mask`).
    path, field: the file and the field that named it, for errors.
    file_size: (width, height) the file must have.
    target_size: (width, height) to return.
    method: resampling method for `resize`.
    size_tolerance: pixels the file may be off `file_size` (pre-downscaled folders round their
      sizes either way).
    size_source: where `file_size` comes from, for errors (e.g. "poses_bounds.npy's hwf").
  Raises:
    InputError: a missing or unreadable file, or one of another size than the cameras give
      (either the file or the camera size is wrong; the message names both).
  """
  try:
    array = read(Path(path))
  except InputError as error:
    if error.field is not None:
      raise
    raise InputError(error.problem, error.path, field) from None
  height, width = array.shape[:2]
  if max(abs(width - file_size[0]), abs(height - file_size[1])) > size_tolerance:
    raise InputError(f"is {width}x{height} pixels, not the {file_size[0]}x{file_size[1]} of "
                     f"{size_source}: the file or the camera size is wrong (every view of a "
                     "dataset has the size of its camera)", path, field)
  return resize(array, *target_size, method)


def prepared_downscale_path(root: Path, relative_path: str, factor: int) -> Path | None:
  """nerfstudio's pre-downscaled copy of a file (`images/x.png` -> `images_4/x.png`), if any."""
  parts = Path(relative_path).parts
  if factor == 1 or len(parts) < 2:
    return None
  folder = f"{parts[0]}_{factor}"
  candidate = root.joinpath(folder, *parts[1:])
  if not candidate.is_file():
    return None
  # The copy is read instead of the file the dataset names: it must stay inside as well.
  return files.contained_path(root, candidate.relative_to(root), root, folder)
