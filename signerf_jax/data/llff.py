"""LLFF forward-facing captures: `poses_bounds.npy` with `images/` and downscaled `images_N/`.

Each row of poses_bounds.npy is a flattened 3x5 matrix [R | t | hwf] followed by the near and far
z-depth bounds of that view's content (from its COLMAP points). R's columns are LLFF's camera
axes [down, right, backwards]; hwf is (height, width, focal) at full resolution. The images of
a folder, in sorted file-name order, belong to the rows in order.

Normalisation (`frame.forward_facing_frame`): as LLFF's `recenter_poses`, the average pose
becomes the identity (the cameras look down -z, y up); then the box around every view's frustum
between its near and far bounds is centred and scaled onto [-1, 1]^3.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from signerf_jax.camera import Cameras
from signerf_jax.data import poses as poses_lib
from signerf_jax.data.capture import Capture, ViewFiles
from signerf_jax.errors import InputError

POSES_NAME = "poses_bounds.npy"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def read_capture(root: str | os.PathLike, downscale: int = 1) -> Capture:
  """Reads an LLFF capture (forward-facing; its frame follows from the rows' depth bounds).

  Args:
    root: the directory holding poses_bounds.npy.
    downscale: image downscale relative to the full resolution in hwf. `images_{downscale}/` is
      used when present, otherwise the closest finer `images_M/` (M divides downscale), to be
      area-resampled; the view names are that folder's files.
  """
  root = Path(root)
  path = root / POSES_NAME
  if not path.is_file():
    raise InputError("file not found", path)
  try:
    rows = np.load(path, allow_pickle=False)
  except (ValueError, OSError, EOFError) as error:
    raise InputError(f"not a readable .npy array ({error})", path) from None
  if not isinstance(rows, np.ndarray):  # np.load opens a zip (.npz) archive whatever its name.
    raise InputError("is an .npz archive, not the single .npy array LLFF writes", path)
  # Only real floating-point values are poses: casting would drop a complex array's imaginary
  # parts (with a mere warning), turn text such as "1.5" into numbers, or fail with a traceback.
  if rows.dtype.kind != "f":
    raise InputError(f"must hold floating-point numbers, got dtype {rows.dtype} (LLFF writes "
                     "float64)", path, "dtype")
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

  folder, folder_factor = _image_folder(root, downscale)
  image_paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
  if len(image_paths) != len(rows):
    raise InputError(f"holds {len(image_paths)} images but {POSES_NAME} has {len(rows)} rows",
                     folder)
  cameras = Cameras.create(np.stack(camera_to_world), fx=np.asarray(focals), width=int(width),
                           height=int(height))
  return Capture(root=root, cameras=cameras,
                 names=tuple(p.relative_to(root).as_posix() for p in image_paths),
                 files=tuple(ViewFiles(image=p, label=f"poses_bounds[{index}]")
                             for index, p in enumerate(image_paths)), depth_bounds=bounds,
                 kind="forward_facing", file_factor=folder_factor, format="llff")


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
