"""COLMAP's sparse model files parsed into records: `cameras`, `images` and `points3D`, binary
(.bin) or text (.txt) (https://colmap.github.io/format.html).

  * cameras: per camera id a model (MODELS_BY_ID), the image size and the model's parameters.
  * images: per registered image its world-to-camera pose in OpenCV axes (qvec = (qw, qx, qy,
    qz), a Hamilton unit quaternion, and tvec: x_camera = R(qvec) x_world + tvec), its camera id
    and its file name (as written: `colmap` checks it stays inside the image folder); the 2D
    keypoints are skipped (in images.txt after checking their line has their form).
  * points3D: the sparse points; only their positions are read.

A corrupt or truncated file is an InputError naming the file and the record at fault; `colmap`
turns the records into a capture's cameras.
"""

from __future__ import annotations

import dataclasses
import os
import re
import struct
from pathlib import Path
from typing import Iterator

import numpy as np

from signerf_jax.errors import InputError

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


# One POINTS2D line: (X Y POINT3D_ID) triples, X and Y decimal numbers, POINT3D_ID an integer
# (-1 for a keypoint without a 3D point); empty for an image without keypoints. Checked as one
# regular expression, linear in the line's length, rather than by parsing millions of numbers.
# Each token matches in one way only (there are no two ways to split "123" between `\d+` and
# `\d*`), so a line that fails fails after one pass, not after exponentially many retries.
_DECIMAL = r"[-+]?(?:(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?|nan|inf(?:inity)?)"
_POINT2D = rf"{_DECIMAL}\s+{_DECIMAL}\s+[-+]?\d+"
_POINTS2D_LINE = re.compile(rf"\s*(?:{_POINT2D}(?:\s+{_POINT2D})*)?\s*", re.IGNORECASE)
IMAGE_LAYOUT = "IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"


def _read_images_text(path: Path) -> list[ColmapImage]:
  """Two lines per image: IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, then its 2D points.

  The line right after an image's line is its POINTS2D line, whatever it holds, as in COLMAP's
  own readers (COLMAP writes it for every image, empty when the image has no keypoints); only
  blank and comment lines before an image's line are skipped. A file written with one line per
  image would otherwise lose every second image into a "points" line, silently, so the points
  line is checked: it must be empty or (X Y POINT3D_ID) triples. One that reads as an image line
  is the tell of a file without points lines, and is refused naming the line; the last image's
  points line may be missing at the end of the file (COLMAP reads that as no points).
  """
  images = []
  lines = _text_lines(path)
  # The name is the rest of the line (it may hold spaces).
  for number, fields in _records(lines, IMAGE_LAYOUT, path, maxsplit=9):
    image_id, camera_id = _numbers([fields[0], fields[8]], int, path, f"line {number}")
    pose = _numbers(fields[1:8], float, path, f"image {image_id}")
    images.append(ColmapImage(image_id, tuple(pose[:4]), tuple(pose[4:]), camera_id,
                              fields[9].strip()))
    points_number, points_line = next(lines, (number + 1, ""))
    if not _POINTS2D_LINE.fullmatch(points_line):
      _refuse_points_line(points_line, image_id, path, f"line {points_number}")
  return images


def _refuse_points_line(line: str, image_id: int, path: Path, field: str) -> None:
  """Raises the InputError for a line that is not the POINTS2D line expected there."""
  if _is_image_line(line):
    raise InputError(
        f"reads as an image line ({IMAGE_LAYOUT}) where image {image_id}'s POINTS2D line is "
        "expected: images.txt holds two lines per image, the image and then its 2D points (an "
        "empty line for an image without any); this file seems to lack the points lines, and "
        "reading it would skip every second image", path, field)
  raise InputError(f"image {image_id}'s POINTS2D line must be empty or (X Y POINT3D_ID) "
                   f"triples, got {line[:60]!r}", path, field)


def _is_image_line(line: str) -> bool:
  """Whether `line` parses as an image line: IMAGE_ID ... CAMERA_ID integers, the pose numbers."""
  fields = line.split(maxsplit=9)
  if len(fields) < 10:
    return False
  try:
    int(fields[0]), int(fields[8])
    [float(value) for value in fields[1:8]]
  except ValueError:
    return False
  return True


def _read_points_text(path: Path) -> tuple[list[int], list[list[float]]]:
  """The points' ids and positions."""
  point_ids, positions = [], []
  for number, fields in _records(_text_lines(path), "POINT3D_ID X Y Z R G B ERROR TRACK[]",
                                 path):
    (point_id,) = _numbers(fields[:1], int, path, f"line {number}")
    point_ids.append(point_id)
    positions.append(_numbers(fields[1:4], float, path, f"point {point_id}"))
  return point_ids, positions
