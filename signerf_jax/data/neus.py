"""NeuS / IDR object captures: `cameras_sphere.npz` (IDR: `cameras.npz`), `image/`, `mask/`.

The npz holds, per view i:
  * `world_mat_i`: the 4x4 (or 3x4) projection P = K [R | t] from the world to pixels, up to
    scale, with pixel centres at whole numbers (NeuS shoots its rays through pixel (j, i) at
    K^-1 (j, i, 1)): this project's principal point is K's plus 0.5;
  * `scale_mat_i` (optional): the similarity mapping NeuS's normalised frame, where the object
    lies inside the unit sphere, into the world. NeuS uses one for all views.
NeuS trains in the normalised frame (P = world_mat @ scale_mat). The capture stays in the
world_mat frame, the user's own units, and the sphere becomes its `object_sphere`: the centre is
scale_mat's translation, the radius its scale.

View i is the i-th image of `image/` (or `images/`) in sorted name order, and the i-th file of
`mask/`, when present, is its object mask: NeuS pairs them the same way. The masks are
black-and-white silhouettes (a first channel above 0.5 is the object, id 1). Images and masks are
PNG (as NeuS reads them) or JPEG.

Each projection is decomposed with cv2.decomposeProjectionMatrix. P is defined up to scale,
sign included: it is divided by its largest entry (so any finite scale, 1e300 or 1e-300, reads
the same cameras), and the sign with det(P[:, :3]) > 0 is the one whose K has positive focal
lengths with R a proper rotation, so it is taken before decomposing.
"""

from __future__ import annotations

import os
import re
import zipfile
import zlib
from pathlib import Path

import cv2
import numpy as np

from signerf_jax import files
from signerf_jax.camera import Cameras
from signerf_jax.data import poses as poses_lib
from signerf_jax.data.capture import Capture, ViewFiles
from signerf_jax.errors import InputError

CAMERA_FILE_NAMES = ("cameras_sphere.npz", "cameras.npz")
IMAGE_FOLDERS = ("image", "images")
MASK_FOLDER = "mask"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
# This project's pixel centres sit at +0.5, NeuS's at whole numbers.
PIXEL_CENTRE_OFFSET = 0.5
# `Cameras` has no skew: a projection whose skew moves pixels by more than this is refused.
SKEW_TOLERANCE_PIXELS = 0.1
# A projection whose 3x3 part has a determinant this small against its scale is singular.
SINGULAR_TOLERANCE = 1e-9
# scale_mat's linear part must be its scale times a rotation, to this relative tolerance.
SIMILARITY_TOLERANCE = 1e-4


def camera_file(root: str | os.PathLike) -> Path | None:
  """The capture's camera file (the first of CAMERA_FILE_NAMES in `root`), or None."""
  candidates = (Path(root) / name for name in CAMERA_FILE_NAMES)
  return next((path for path in candidates if path.is_file()), None)


def read_capture(root: str | os.PathLike) -> Capture:
  """Reads a NeuS / IDR capture (see the module docstring), in the world_mat frame.

  Raises:
    InputError: naming the file and the key at fault: a missing or extra world_mat_i, a matrix
      that is not a camera projection, scale_mats that are not one similarity, or masks that do
      not pair with the images.
  """
  root = Path(root)
  path = camera_file(root)
  if path is None:
    raise InputError(f"none of {list(CAMERA_FILE_NAMES)} found", root)
  try:
    with np.load(path, allow_pickle=False) as archive:
      arrays = {key: archive[key] for key in archive.files}
  except (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error) as error:
    raise InputError(f"not a readable .npz archive ({error})", path) from None

  image_paths = _images(_image_folder(root))
  _check_world_mat_keys(arrays, len(image_paths), path)
  height, width = files.read_image(image_paths[0]).shape[:2]
  camera_to_world, intrinsics = [], []
  for index in range(len(image_paths)):
    pose, view_intrinsics = _decompose(arrays[f"world_mat_{index}"], height, path,
                                       f"world_mat_{index}")
    camera_to_world.append(pose)
    intrinsics.append(view_intrinsics)
  fx, fy, cx, cy = np.asarray(intrinsics).T
  mask_paths = _masks(root, len(image_paths))
  return Capture(
      root=root,
      cameras=Cameras.create(np.stack(camera_to_world), fx, fy, cx, cy, width=width,
                             height=height),
      names=tuple(image.relative_to(root).as_posix() for image in image_paths),
      files=tuple(ViewFiles(image=image, object_mask=mask,
                            label=f"{path.name}: world_mat_{index}")
                  for index, (image, mask) in enumerate(zip(image_paths, mask_paths))),
      object_sphere=_object_sphere(arrays, len(image_paths), path),
      silhouette_masks=True,
      format="neus",
  )


def _image_folder(root: Path) -> Path:
  for name in IMAGE_FOLDERS:
    if (root / name).is_dir():
      return root / name
  raise InputError(f"no image folder: none of {list(IMAGE_FOLDERS)} found", root)


def _images(folder: Path) -> list[Path]:
  """The images of `folder` in sorted name order (at least one)."""
  paths = sorted(path for path in folder.iterdir() if path.suffix.lower() in IMAGE_SUFFIXES)
  if not paths:
    raise InputError(f"holds no {'/'.join(IMAGE_SUFFIXES)} images", folder)
  return paths


def _masks(root: Path, count: int) -> list[Path | None]:
  """Each view's mask (NeuS pairs the sorted masks with the sorted images), or Nones."""
  folder = root / MASK_FOLDER
  if not folder.is_dir():
    return [None] * count
  masks = _images(folder)
  if len(masks) != count:
    raise InputError(f"holds {len(masks)} masks but there are {count} images (NeuS pairs them "
                     "in sorted order: one mask per image)", folder)
  return masks


def _check_world_mat_keys(arrays: dict[str, np.ndarray], count: int, path: Path) -> None:
  """world_mat_0 ... world_mat_{count - 1}, one per image, and no others."""
  indices = {int(key[len("world_mat_"):]) for key in arrays
             if re.fullmatch(r"world_mat_\d+", key)}
  missing = [index for index in range(count) if index not in indices]
  if missing:
    raise InputError(f"missing: the image folder holds {count} images, each needs its "
                     "world_mat", path, f"world_mat_{missing[0]}")
  extra = sorted(index for index in indices if index >= count)
  if extra:
    raise InputError(f"has no image: the image folder holds only {count} (images missing, or "
                     "cameras of another capture?)", path, f"world_mat_{extra[0]}")


def _matrix(value: np.ndarray, shapes: tuple[tuple[int, int], ...], path: Path,
            key: str) -> np.ndarray:
  """A finite float64 matrix of one of `shapes`.

  A 4x4 matrix is homogeneous: its last row must be [0, 0, 0, w] with w != 0 (NeuS and IDR
  write w = 1), and it is returned divided by w, the same map (a world_mat scaled as a whole is
  the same projection; a scale_mat with w = 2 halves what it maps).
  """
  value = np.asarray(value)
  # Real numbers only: a cast would drop a complex matrix's imaginary parts (with a mere
  # warning) or read text such as "1.5" as a number.
  if value.dtype.kind not in "fiu":
    raise InputError(f"must hold real numbers, got dtype {value.dtype}", path, key)
  matrix = value.astype(np.float64)
  if matrix.shape not in shapes or not np.all(np.isfinite(matrix)):
    expected = " or ".join(f"{rows}x{columns}" for rows, columns in shapes)
    raise InputError(f"must be a finite {expected} matrix, got shape {matrix.shape}", path,
                     key)
  if matrix.shape == (4, 4):
    last_row = matrix[3]
    if last_row[3] == 0 or not np.allclose(last_row[:3] / last_row[3], 0):
      raise InputError(f"last row must be [0, 0, 0, 1] (or a multiple), got {last_row.tolist()}",
                       path, key)
    matrix = matrix / last_row[3]
    matrix[3] = [0, 0, 0, 1]
    if not np.all(np.isfinite(matrix)):
      raise InputError(f"overflows once divided by its last row's {last_row[3]:.3g}", path, key)
  return matrix


def _decompose(world_mat: np.ndarray, height: int, path: Path, key: str):
  """One projection's OpenGL camera-to-world [3, 4] and intrinsics (fx, fy, cx, cy) in this
  project's pixel convention, for images `height` pixels high."""
  projection = _matrix(world_mat, ((3, 4), (4, 4)), path, key)[:3]
  # P is defined up to scale: dividing by its largest entry first lets a projection scaled by
  # 1e300 (or 1e-300) decompose like any other instead of overflowing (underflowing) the
  # determinant below, which would call it singular.
  largest = np.max(np.abs(projection))
  if largest == 0:
    raise InputError("is all zeros: not a camera projection K [R | t]", path, key)
  projection = projection / largest
  determinant = np.linalg.det(projection[:, :3])
  if abs(determinant) <= SINGULAR_TOLERANCE * np.prod(np.linalg.norm(projection[:, :3], axis=1)):
    raise InputError("is singular: not a camera projection K [R | t]", path, key)
  if determinant < 0:
    projection = -projection
  intrinsics, rotation = cv2.decomposeProjectionMatrix(projection)[:2]
  # The RQ decomposition fixes K and R up to the signs of K's columns / R's rows.
  signs = np.diag(np.sign(np.diag(intrinsics)))
  intrinsics, rotation = intrinsics @ signs, signs @ rotation
  intrinsics = intrinsics / intrinsics[2, 2]
  if np.linalg.det(rotation) < 0:
    raise InputError("does not decompose into a proper rotation", path, key)
  fx, skew, cx = intrinsics[0]
  fy, cy = intrinsics[1, 1:]
  # Skew shifts a pixel sideways in proportion to its row's distance from the principal point.
  skew_shift = abs(skew) * max(cy, height - cy) / fy
  if skew_shift > SKEW_TOLERANCE_PIXELS:
    raise InputError(f"has skew {skew:.4g}, which moves pixels by up to {skew_shift:.2g} px; "
                     "this project's cameras have none", path, key)
  centre = -np.linalg.solve(projection[:, :3], projection[:, 3])
  camera_to_world = poses_lib.camera_to_world_from_opencv(rotation, -rotation @ centre)
  return camera_to_world, (fx, fy, cx + PIXEL_CENTRE_OFFSET, cy + PIXEL_CENTRE_OFFSET)


def _object_sphere(arrays: dict[str, np.ndarray], count: int, path: Path):
  """(centre [3], radius) of scale_mat_0's unit sphere in the world, or None without one."""
  if "scale_mat_0" not in arrays:
    return None
  scale_mat = _matrix(arrays["scale_mat_0"], ((4, 4),), path, "scale_mat_0")
  for index in range(1, count):
    key = f"scale_mat_{index}"
    if key in arrays and not np.allclose(_matrix(arrays[key], ((4, 4),), path, key), scale_mat):
      raise InputError("differs from scale_mat_0: NeuS's normalised frame (and the object's "
                       "sphere) is one for all views", path, key)
  # Tested on the linear part divided by its largest entry: the determinant of a similarity
  # scaled by 1e300 would overflow (and one scaled by 1e-300 underflow) unnormalised.
  largest = np.max(np.abs(scale_mat[:3, :3]))
  linear = scale_mat[:3, :3] / largest if largest > 0 else scale_mat[:3, :3]
  unit_radius = np.cbrt(np.linalg.det(linear))
  radius = unit_radius * largest
  deviation = np.max(np.abs(linear.T @ linear - unit_radius**2 * np.eye(3)))
  if not (unit_radius > 0 and 0 < radius < np.inf
          and deviation <= SIMILARITY_TOLERANCE * unit_radius**2):
    raise InputError("must be a similarity (uniform positive scale, rotation, translation), got "
                     f"{scale_mat.tolist()}", path, "scale_mat_0")
  return scale_mat[:3, 3].copy(), float(radius)
