"""COLMAP sparse reconstructions: `cameras`, `images` and `points3D`, binary (.bin) or text (.txt).

Layout (https://colmap.github.io/format.html): the model files in `root/sparse/0/`, else in
`root/sparse/`, else in `root/` (the first of these folders holding both a cameras and an images
file; each file is read as .bin when present, else as .txt), the images in `root/images/<name>`
(`load.load_dataset` uses downscaled copies in `root/images_N/` where they exist).

  * cameras: per camera id a model, the image size and the model's parameters. Every COLMAP
    model with an OpenCV equivalent maps exactly (SUPPORTED_MODELS): the parameters after the
    focal length(s) and the principal point are OpenCV's coefficients in OpenCV's order. COLMAP
    puts the centre of the top-left pixel at (0.5, 0.5), as this project does, so the principal
    point carries over unchanged.
  * images: per registered image its world-to-camera pose in OpenCV axes (qvec = (qw, qx, qy, qz),
    a Hamilton unit quaternion, and tvec: x_camera = R(qvec) x_world + tvec), its camera id and
    its file name; the 2D keypoints are skipped.
  * points3D: the sparse points; only their positions are read.

Views are sorted by image name (COLMAP numbers images in the order it registered them, not the
order they were taken). The capture has no split of its own. All views must share one image
size and one kind of lens (fisheye or perspective), as `Cameras` does.
"""

from __future__ import annotations

import dataclasses
import os
import struct
from pathlib import Path
from typing import Iterator

import numpy as np

from signerf_jax.camera import DISTORTION_SIZE, Cameras
from signerf_jax.data import poses as poses_lib
from signerf_jax.data.capture import Capture, ViewFiles
from signerf_jax.errors import InputError

# Where the model files are looked for, in order, relative to the dataset root.
MODEL_FOLDERS = ("sparse/0", "sparse", ".")
IMAGE_FOLDER = "images"
MODEL_FILE_SUFFIXES = (".bin", ".txt")
# COLMAP's model ids and parameter counts (src/colmap/sensor/models.h). The binary cameras file
# stores only the id, so the count is needed to read past any camera, supported or not.
MODELS_BY_ID = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
    4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16), 12: ("SIMPLE_DIVISION", 4), 13: ("DIVISION", 5),
    14: ("SIMPLE_FISHEYE", 3), 15: ("FISHEYE", 4), 16: ("EUCM", 6), 17: ("EQUIRECTANGULAR", 2),
}
PARAMETER_COUNTS = dict(MODELS_BY_ID.values())


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


@dataclasses.dataclass(frozen=True)
class ColmapCamera:
  """One camera of a cameras file: its id, model name, image size and parameters."""

  camera_id: int
  model: str
  width: int
  height: int
  params: tuple[float, ...]


@dataclasses.dataclass(frozen=True)
class ColmapImage:
  """One registered image of an images file.

  Attributes:
    quaternion: (qw, qx, qy, qz) of the world-to-camera rotation (OpenCV camera axes).
    translation: (tx, ty, tz), x_camera = R x_world + translation.
  """

  image_id: int
  quaternion: tuple[float, float, float, float]
  translation: tuple[float, float, float]
  camera_id: int
  name: str


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
      unsupported camera model, a corrupt or truncated file, images of mixed sizes or lenses.
  """
  root = Path(root)
  folder = model_folder(root)
  if folder is None:
    raise InputError("no COLMAP model found: none of "
                     f"{[str(Path(relative) / 'cameras.bin') for relative in MODEL_FOLDERS]} "
                     "(or .txt) with an images file beside it", root)
  cameras_path, images_path = _model_file(folder, "cameras"), _model_file(folder, "images")
  colmap_cameras = read_cameras(cameras_path)
  images = sorted(read_images(images_path), key=lambda image: image.name)
  if not images:
    raise InputError("holds no registered images", images_path)
  for previous, image in zip(images, images[1:]):
    if image.name == previous.name:
      raise InputError(f"names {image.name!r} again (image {previous.image_id} has it too)",
                       images_path, f"image {image.image_id}")

  lenses, camera_to_world = [], []
  for image in images:
    label = f"image {image.image_id}"
    if image.camera_id not in colmap_cameras:
      raise InputError(f"its camera {image.camera_id} is not in {cameras_path.name}", images_path,
                       label)
    lenses.append(_Lens.of(colmap_cameras[image.camera_id], cameras_path))
    camera_to_world.append(poses_lib.camera_to_world_from_opencv(
        _rotation(image.quaternion, images_path, label), image.translation))
  _check_one_size_and_lens_kind(lenses, cameras_path)

  points_path = _model_file(folder, "points3D")
  points = read_points(points_path) if points_path else np.zeros((0, 3))
  cameras = Cameras.create(
      np.stack(camera_to_world), fx=[lens.fx for lens in lenses], fy=[lens.fy for lens in lenses],
      cx=[lens.cx for lens in lenses], cy=[lens.cy for lens in lenses],
      distortion=np.stack([lens.distortion for lens in lenses]), width=lenses[0].width,
      height=lenses[0].height, fisheye=lenses[0].fisheye)
  return Capture(
      root=root,
      cameras=cameras,
      names=tuple(f"{IMAGE_FOLDER}/{image.name}" for image in images),
      files=tuple(ViewFiles(image=root / IMAGE_FOLDER / image.name,
                            label=f"{images_path.name}: image {image.image_id}")
                  for image in images),
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
  def of(cls, camera: ColmapCamera, path: Path) -> "_Lens":
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


def read_cameras(path: str | os.PathLike) -> dict[int, ColmapCamera]:
  """The cameras of a `cameras.bin` / `cameras.txt`, by camera id."""
  path = Path(path)
  records = _read_cameras_binary(path) if path.suffix == ".bin" else _read_cameras_text(path)
  cameras = {}
  for camera in records:
    if camera.camera_id in cameras:
      raise InputError("appears twice", path, f"camera {camera.camera_id}")
    cameras[camera.camera_id] = camera
  return cameras


def read_images(path: str | os.PathLike) -> list[ColmapImage]:
  """The registered images of an `images.bin` / `images.txt`, in file order."""
  path = Path(path)
  return _read_images_binary(path) if path.suffix == ".bin" else _read_images_text(path)


def read_points(path: str | os.PathLike) -> np.ndarray:
  """[P, 3] float64 positions of the points of a `points3D.bin` / `points3D.txt`."""
  path = Path(path)
  point_ids, positions = (_read_points_binary(path) if path.suffix == ".bin"
                          else _read_points_text(path))
  positions = np.asarray(positions, np.float64).reshape(-1, 3)
  bad = np.flatnonzero(~np.all(np.isfinite(positions), axis=-1))
  if len(bad):
    raise InputError(f"has non-finite position {positions[bad[0]].tolist()}", path,
                     f"point {point_ids[bad[0]]}")
  return positions


class _BinaryFile:
  """Little-endian values read in order from a COLMAP binary file. Running out of bytes is an
  InputError naming the file and the record being read, never a struct error."""

  def __init__(self, path: Path):
    self.path = path
    try:
      self.data = path.read_bytes()
    except OSError as error:
      raise InputError(f"cannot be read ({error.strerror})", path) from None
    self.offset = 0

  def read(self, layout: str, field: str) -> tuple:
    """The values of struct `layout` (without byte order) at the current offset."""
    layout = "<" + layout
    self._require(struct.calcsize(layout), field)
    values = struct.unpack_from(layout, self.data, self.offset)
    self.offset += struct.calcsize(layout)
    return values

  def read_count(self, smallest_record: int, field: str) -> int:
    """A uint64 record count, checked against the bytes left (a corrupt count would otherwise
    loop or allocate for billions of records)."""
    (count,) = self.read("Q", field)
    self._require(count * smallest_record, f"{field} ({count} records)")
    return count

  def read_name(self, field: str) -> str:
    """A zero-terminated UTF-8 string."""
    end = self.data.find(b"\0", self.offset)
    if end < 0:
      raise InputError("truncated: the image name has no terminating zero byte", self.path,
                       field)
    raw, self.offset = self.data[self.offset:end], end + 1
    try:
      return raw.decode("utf-8")
    except UnicodeDecodeError:
      raise InputError(f"image name {raw[:40]!r} is not UTF-8 text (corrupt file?)", self.path,
                       field) from None

  def skip(self, size: int, field: str) -> None:
    self._require(size, field)
    self.offset += size

  def check_finished(self) -> None:
    if self.offset != len(self.data):
      raise InputError(f"{len(self.data) - self.offset} bytes follow the last record (corrupt, or "
                       "not a COLMAP model file)", self.path)

  def _require(self, size: int, field: str) -> None:
    if self.offset + size > len(self.data):
      raise InputError(f"truncated: {size} bytes are needed at byte {self.offset} but the file "
                       f"ends at byte {len(self.data)}", self.path, field)


# Record layouts of the binary files, without byte order (all little-endian):
# camera: camera_id uint32, model_id int32, width, height uint64; then the model's float64 params.
CAMERA_HEADER = "IiQQ"
# image: image_id uint32, qw qx qy qz tx ty tz float64, camera_id uint32; then the name
# (zero-terminated), the number of 2D points (uint64) and the points (x, y float64, point3D_id
# int64 each).
IMAGE_HEADER = "I7dI"
POINT2D_SIZE = 24
# point: point3D_id uint64, x y z float64, r g b uint8, error float64, track length uint64; then
# the track (image_id, point2D_index uint32 each).
POINT_HEADER = "Q3d3BdQ"
TRACK_ELEMENT_SIZE = 8


def _read_cameras_binary(path: Path) -> list[ColmapCamera]:
  file = _BinaryFile(path)
  cameras = []
  for index in range(file.read_count(struct.calcsize("<" + CAMERA_HEADER), "number of cameras")):
    camera_id, model_id, width, height = file.read(CAMERA_HEADER, f"camera record {index}")
    label = f"camera {camera_id}"
    if model_id not in MODELS_BY_ID:
      raise InputError(f"unknown camera model id {model_id} (corrupt file, or a model newer than "
                       "this reader)", path, label)
    model, parameter_count = MODELS_BY_ID[model_id]
    params = file.read(f"{parameter_count}d", label)
    cameras.append(ColmapCamera(camera_id, model, width, height, params))
  file.check_finished()
  return cameras


def _read_images_binary(path: Path) -> list[ColmapImage]:
  file = _BinaryFile(path)
  images = []
  # The smallest image record: its header, an empty name and no points.
  smallest_record = struct.calcsize("<" + IMAGE_HEADER) + 1 + 8
  for index in range(file.read_count(smallest_record, "number of images")):
    image_id, *pose, camera_id = file.read(IMAGE_HEADER, f"image record {index}")
    label = f"image {image_id}"
    name = file.read_name(label)
    (point_count,) = file.read("Q", label)
    file.skip(point_count * POINT2D_SIZE, label)
    images.append(ColmapImage(image_id, tuple(pose[:4]), tuple(pose[4:]), camera_id, name))
  file.check_finished()
  return images


def _read_points_binary(path: Path) -> tuple[list[int], list[tuple[float, float, float]]]:
  """The points' ids and positions."""
  file = _BinaryFile(path)
  point_ids, positions = [], []
  for index in range(file.read_count(struct.calcsize("<" + POINT_HEADER), "number of points")):
    point_id, x, y, z, *_, track_length = file.read(POINT_HEADER, f"point record {index}")
    file.skip(track_length * TRACK_ELEMENT_SIZE, f"point {point_id}")
    point_ids.append(point_id)
    positions.append((x, y, z))
  file.check_finished()
  return point_ids, positions


def _text_lines(path: Path) -> Iterator[tuple[int, str]]:
  """(line number, line) of every line of a text model file."""
  try:
    text = path.read_text(encoding="utf-8")
  except (OSError, UnicodeDecodeError) as error:
    raise InputError(f"cannot be read as UTF-8 text ({error})", path) from None
  return enumerate(text.splitlines(), start=1)


def _records(lines: Iterator[tuple[int, str]], layout: str, path: Path,
             maxsplit: int = -1) -> Iterator[tuple[int, list[str]]]:
  """(line number, fields) of each line of `lines` that holds data (neither blank nor a
  comment); it must hold the fields `layout` names (a trailing `NAME[]` list may be empty)."""
  required = len([name for name in layout.split() if not name.endswith("[]")])
  for number, line in lines:
    if not line.strip() or line.lstrip().startswith("#"):
      continue
    fields = line.split(maxsplit=maxsplit)
    if len(fields) < required:
      raise InputError(f"needs {layout}", path, f"line {number}")
    yield number, fields


def _numbers(values: list[str], kind: type, path: Path, field: str) -> list:
  """`values` parsed as `kind` (int or float)."""
  try:
    return [kind(value) for value in values]
  except ValueError:
    raise InputError(f"{' '.join(values)!r} are not {kind.__name__} values", path,
                     field) from None


def _read_cameras_text(path: Path) -> list[ColmapCamera]:
  cameras = []
  for number, fields in _records(_text_lines(path), "CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]",
                                 path):
    camera_id, width, height = _numbers([fields[0], *fields[2:4]], int, path, f"line {number}")
    label, model = f"camera {camera_id}", fields[1]
    if model not in PARAMETER_COUNTS:
      raise InputError(f"unknown camera model {model!r}", path, label)
    params = _numbers(fields[4:], float, path, label)
    if len(params) != PARAMETER_COUNTS[model]:
      raise InputError(f"{model} has {PARAMETER_COUNTS[model]} parameters, got {len(params)}",
                       path, label)
    cameras.append(ColmapCamera(camera_id, model, width, height, tuple(params)))
  return cameras


def _read_images_text(path: Path) -> list[ColmapImage]:
  """Two lines per image: IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, then its 2D points
  (the line right after, blank when it has none: it is skipped)."""
  images = []
  lines = _text_lines(path)
  # The name is the rest of the line (it may hold spaces).
  for number, fields in _records(lines, "IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME", path,
                                 maxsplit=9):
    image_id, camera_id = _numbers([fields[0], fields[8]], int, path, f"line {number}")
    pose = _numbers(fields[1:8], float, path, f"image {image_id}")
    images.append(ColmapImage(image_id, tuple(pose[:4]), tuple(pose[4:]), camera_id,
                              fields[9].strip()))
    next(lines, None)  # The image's 2D points.
  return images


def _read_points_text(path: Path) -> tuple[list[int], list[list[float]]]:
  """The points' ids and positions."""
  point_ids, positions = [], []
  for number, fields in _records(_text_lines(path), "POINT3D_ID X Y Z R G B ERROR TRACK[]",
                                 path):
    (point_id,) = _numbers(fields[:1], int, path, f"line {number}")
    point_ids.append(point_id)
    positions.append(_numbers(fields[1:4], float, path, f"point {point_id}"))
  return point_ids, positions
