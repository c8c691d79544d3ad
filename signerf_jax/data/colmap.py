"""COLMAP sparse reconstructions as a `Capture`: where the model is, and its cameras and poses
converted to `Cameras` (`colmap_model` parses the files themselves).

Layout (https://colmap.github.io/format.html): the model files in `root/sparse/0/`, else in
`root/sparse/`, else in `root/` (the first of these folders holding both a cameras and an images
file; each file is read as .bin when present, else as .txt), the images in `root/images/<name>`
(`load.load_dataset` uses downscaled copies in `root/images_N/` where they exist).

Every COLMAP camera model with an OpenCV equivalent maps exactly (SUPPORTED_MODELS): the
parameters after the focal length(s) and the principal point are OpenCV's coefficients in
OpenCV's order. COLMAP puts the centre of the top-left pixel at (0.5, 0.5), as this project
does, so the principal point carries over unchanged. Each image's world-to-camera pose (OpenCV
axes) becomes a camera-to-world; of the sparse points only their positions are kept.

Views are sorted by image name (COLMAP numbers images in the order it registered them, not the
order they were taken). The capture has no split of its own. All views must share one image
size and one kind of lens (fisheye or perspective), as `Cameras` does.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

from signerf_jax import files
from signerf_jax.camera import Cameras
from signerf_jax.data import colmap_model
from signerf_jax.data import poses as poses_lib
from signerf_jax.data.capture import Capture, ViewFiles
from signerf_jax.errors import InputError
from signerf_jax.lens import DISTORTION_SIZE

# Where the model files are looked for, in order, relative to the dataset root.
MODEL_FOLDERS = ("sparse/0", "sparse", ".")
IMAGE_FOLDER = "images"
MODEL_FILE_SUFFIXES = (".bin", ".txt")


@dataclasses.dataclass(frozen=True)
class LensLayout:
  """How a COLMAP model's parameters become `Cameras` intrinsics.

  Attributes:
    focal_lengths: 1 (parameters f, cx, cy, ...) or 2 (fx, fy, cx, cy, ...).
    fisheye: the lens follows cv2.fisheye's model (else OpenCV's perspective one).
  The parameters after the principal point are OpenCV's coefficients in OpenCV's order
  (perspective k1, k2, p1, p2, k3, k4, k5, k6; fisheye k1, k2, k3, k4): they fill
  `Cameras.distortion` from its first slot.
  """

  focal_lengths: int
  fisheye: bool


SUPPORTED_MODELS = {
    "SIMPLE_PINHOLE": LensLayout(1, False),
    "PINHOLE": LensLayout(2, False),
    "SIMPLE_RADIAL": LensLayout(1, False),  # k = OpenCV's k1
    "RADIAL": LensLayout(1, False),  # k1, k2
    "OPENCV": LensLayout(2, False),  # k1, k2, p1, p2
    "FULL_OPENCV": LensLayout(2, False),  # k1, k2, p1, p2, k3, k4, k5, k6
    "OPENCV_FISHEYE": LensLayout(2, True),  # k1, k2, k3, k4
    # theta_d = theta (1 + k theta^2) and theta (1 + k1 theta^2 + k2 theta^4): cv2.fisheye's
    # model with the higher coefficients zero.
    "SIMPLE_RADIAL_FISHEYE": LensLayout(1, True),
    "RADIAL_FISHEYE": LensLayout(1, True),
    # Equidistant (theta_d = theta): cv2.fisheye's model with every coefficient zero.
    "SIMPLE_FISHEYE": LensLayout(1, True),
    "FISHEYE": LensLayout(2, True),
}
# Why the other models have no OpenCV equivalent.
UNSUPPORTED_MODELS = {
    "FOV": "its arctangent (field-of-view) distortion",
    "THIN_PRISM_FISHEYE": "its tangential and thin-prism terms on equidistant coordinates",
    "RAD_TAN_THIN_PRISM_FISHEYE": "its tangential and thin-prism terms on equidistant coordinates",
    "SIMPLE_DIVISION": "its division distortion", "DIVISION": "its division distortion",
    "EUCM": "its enhanced unified projection",
    "EQUIRECTANGULAR": "it is a spherical panorama, not a lens",
}
# A stored quaternion this far from unit length is not a rotation but a corrupt record.
QUATERNION_NORM_TOLERANCE = 1e-2


def model_folder(root: str | os.PathLike) -> Path | None:
  """The first of MODEL_FOLDERS under `root` holding a cameras and an images file, or None."""
  for relative in MODEL_FOLDERS:
    folder = Path(root) / relative
    if _model_file(folder, "cameras") and _model_file(folder, "images"):
      return folder
  return None


def _model_file(folder: Path, stem: str) -> Path | None:
  """`folder/stem.bin`, else `folder/stem.txt`, else None."""
  candidates = (folder / f"{stem}{suffix}" for suffix in MODEL_FILE_SUFFIXES)
  return next((path for path in candidates if path.is_file()), None)


def read_capture(root: str | os.PathLike) -> Capture:
  """Reads the COLMAP model under `root` (see the module docstring for where it is looked for).

  Raises:
    InputError: naming the file and the record at fault (e.g. `images.bin`, `image 7`): an
      unsupported camera model, a corrupt or truncated file, images of mixed sizes or lenses,
      an image name leading outside `root/images` (`../x.png`, an absolute path, a symlink).
  """
  root = Path(root)
  folder = model_folder(root)
  if folder is None:
    raise InputError("no COLMAP model found: none of "
                     f"{[str(Path(relative) / 'cameras.bin') for relative in MODEL_FOLDERS]} "
                     "(or .txt) with an images file beside it", root)
  cameras_path, images_path = _model_file(folder, "cameras"), _model_file(folder, "images")
  colmap_cameras = colmap_model.read_cameras(cameras_path)
  images = sorted(colmap_model.read_images(images_path), key=lambda image: image.name)
  if not images:
    raise InputError("holds no registered images", images_path)
  for previous, image in zip(images, images[1:]):
    if image.name == previous.name:
      raise InputError(f"names {image.name!r} again (image {previous.image_id} has it too)",
                       images_path, f"image {image.image_id}")

  lenses, camera_to_world, image_paths = [], [], []
  for image in images:
    label = f"image {image.image_id}"
    # A name is a path relative to the image folder, as COLMAP was given it; `../../x` or an
    # absolute path would read (and copy into a run's outputs) a file outside the dataset.
    image_paths.append(files.contained_path(root / IMAGE_FOLDER, image.name, images_path, label))
    if image.camera_id not in colmap_cameras:
      raise InputError(f"its camera {image.camera_id} is not in {cameras_path.name}", images_path,
                       label)
    lenses.append(_Lens.of(colmap_cameras[image.camera_id], cameras_path))
    camera_to_world.append(poses_lib.camera_to_world_from_opencv(
        _rotation(image.quaternion, images_path, label), image.translation))
  _check_one_size_and_lens_kind(lenses, cameras_path)

  points_path = _model_file(folder, "points3D")
  points = colmap_model.read_points(points_path) if points_path else np.zeros((0, 3))
  cameras = Cameras.create(
      np.stack(camera_to_world), fx=[lens.fx for lens in lenses], fy=[lens.fy for lens in lenses],
      cx=[lens.cx for lens in lenses], cy=[lens.cy for lens in lenses],
      distortion=np.stack([lens.distortion for lens in lenses]), width=lenses[0].width,
      height=lenses[0].height, fisheye=lenses[0].fisheye)
  return Capture(
      root=root,
      cameras=cameras,
      names=tuple(f"{IMAGE_FOLDER}/{image.name}" for image in images),
      files=tuple(ViewFiles(image=path, label=f"{images_path.name}: image {image.image_id}")
                  for image, path in zip(images, image_paths)),
      points=points if len(points) else None,
      format="colmap",
  )


@dataclasses.dataclass(frozen=True)
class _Lens:
  """One COLMAP camera's validated intrinsics, as `Cameras` holds them.

  Attributes:
    distortion: [8] float64 (see `Cameras.distortion`).
    label: "camera <id>", for errors.
  """

  fx: float
  fy: float
  cx: float
  cy: float
  distortion: np.ndarray
  fisheye: bool
  width: int
  height: int
  label: str

  @classmethod
  def of(cls, camera: colmap_model.ColmapCamera, path: Path) -> "_Lens":
    label = f"camera {camera.camera_id}"
    if camera.model in UNSUPPORTED_MODELS:
      raise InputError(f"uses COLMAP's {camera.model} model, which has no OpenCV equivalent "
                       f"({UNSUPPORTED_MODELS[camera.model]}); supported: "
                       f"{', '.join(SUPPORTED_MODELS)}", path, label)
    layout = SUPPORTED_MODELS[camera.model]
    params = np.asarray(camera.params, np.float64)
    if not np.all(np.isfinite(params)):
      raise InputError(f"has non-finite parameters {params.tolist()}", path, label)
    if min(camera.width, camera.height) < 1:
      raise InputError(f"image size {camera.width}x{camera.height} is empty", path, label)
    focal = [poses_lib.check_focal_length(float(value), path, label)
             for value in params[:layout.focal_lengths]]
    cx, cy = params[layout.focal_lengths:layout.focal_lengths + 2]
    distortion = np.zeros(DISTORTION_SIZE)
    coefficients = params[layout.focal_lengths + 2:]
    distortion[:len(coefficients)] = coefficients
    return cls(fx=focal[0], fy=focal[-1], cx=float(cx), cy=float(cy), distortion=distortion,
               fisheye=layout.fisheye, width=camera.width, height=camera.height, label=label)


def _check_one_size_and_lens_kind(lenses: list[_Lens], path: Path) -> None:
  """Every view's camera has the first one's image size and kind of lens (`Cameras` holds one)."""
  first = lenses[0]
  kinds = {True: "a fisheye", False: "a perspective"}
  for lens in lenses:
    if (lens.width, lens.height) != (first.width, first.height):
      raise InputError(f"images are {lens.width}x{lens.height} but {first.label}'s are "
                       f"{first.width}x{first.height} (images of mixed sizes; resize them, or "
                       "reconstruct them apart)", path, lens.label)
    if lens.fisheye != first.fisheye:
      raise InputError(f"is {kinds[lens.fisheye]} lens but {first.label} is "
                       f"{kinds[first.fisheye]} one (a dataset has one kind of lens)", path,
                       lens.label)


def _rotation(quaternion, path: Path, field: str) -> np.ndarray:
  """[3, 3] rotation of a Hamilton quaternion (qw, qx, qy, qz) of (nearly) unit length."""
  quaternion = np.asarray(quaternion, np.float64)
  norm = np.linalg.norm(quaternion)
  if not np.isfinite(norm) or abs(norm - 1) > QUATERNION_NORM_TOLERANCE:
    raise InputError(f"qvec {quaternion.tolist()} is not a unit quaternion (corrupt record?)", path,
                     field)
  w, x, y, z = quaternion / norm
  return np.array([
      [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
  ])


