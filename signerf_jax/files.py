"""Reading and writing files: atomic writes, JSON, 8/16-bit images and EXR depth maps, and the
paths a data file names, kept inside its folder (`contained_path`).

Every writer goes through `atomic_path`, so an interrupted run never leaves a half-written file:
the data lands in a temporary file next to the target, is flushed to disk, and is renamed over
the target only when complete.
"""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path
from typing import Any, Iterator

import cv2
import numpy as np

from signerf_jax import ownership
from signerf_jax.errors import InputError


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
  """Yields a temporary path in `path`'s directory; renames it onto `path` on success.

  The temporary name keeps `path`'s suffix so format-sniffing writers (OpenCV, OpenEXR) work.
  Inside a directory a command claimed, the write is recorded and a file the project did not
  write is never replaced (`ownership.prepare_write`).

  Raises:
    InputError naming `path`: it is a user's file in a claimed directory, or the disk is full
      (the file `path` held before, if any, is left as it was).
  """
  path = Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  temporary = ownership.prepare_write(path)
  # Created with the permissions a plain open() would give (mkstemp would make it 0600).
  os.close(os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
  try:
    yield temporary
    # On disk before the rename, and the rename itself on disk after it: a power loss leaves the
    # old file or the new one, never an empty or partial file under the target's name.
    _fsync(temporary, os.O_RDONLY)
    os.replace(temporary, path)
    _fsync(path.parent, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
  except BaseException as error:
    with contextlib.suppress(FileNotFoundError):
      os.remove(temporary)
    if isinstance(error, OSError) and ownership.is_disk_full(error):
      raise InputError(f"could not be written: {error.strerror}; the file it replaces, if any, "
                       "is kept: free some space and run the command again", path) from None
    raise


def _fsync(path: str | os.PathLike, flags: int) -> None:
  descriptor = os.open(path, flags)
  try:
    os.fsync(descriptor)
  finally:
    os.close(descriptor)


def contained_path(root: str | os.PathLike, relative: str | os.PathLike,
                   source: str | os.PathLike, field: str, *, follow_links: bool = True) -> Path:
  """`root / relative`, refused unless it lies inside `root`.

  A data file names other files by paths relative to its folder (a dataset its images, masks
  and depth maps; a weights index its shards); a path such as `../../secret.png`, an absolute
  path elsewhere or (with `follow_links`) a symbolic link leading out would make a run read, and
  later copy into its outputs, a file the user never put there. An absolute path that does lie
  inside `root` is accepted; a `root` that is itself a symbolic link is fine.

  Args:
    root: the folder.
    relative: the path as written in `source` (relative to `root`, or absolute).
    source: the file that named the path (e.g. transforms.json), for errors.
    field: the entry that named it (e.g. "frames[3].file_path"), for errors.
    follow_links: check where symbolic links lead (datasets); False checks the path as written
      (a model folder, whose files are links into a download cache by design).
  Returns:
    `root / relative` as written (not resolved: messages then show the path the user knows). It
    need not exist: readers report a missing file.
  Raises:
    InputError naming `source` and `field`: not a path, an empty one, or one outside `root`.
  """
  if not isinstance(relative, (str, os.PathLike)):
    raise InputError(f"expected a path (a string), found {relative!r}", source, field)
  text = os.fspath(relative)
  if not isinstance(text, str) or not text.strip():
    raise InputError("is an empty path; expected a file inside the folder", source, field)
  if "\0" in text:
    raise InputError(f"{text!r} is not a valid path (it contains a NUL character)", source, field)
  joined = Path(root) / text  # An absolute `text` stays as it is.
  try:
    if follow_links:
      resolved_root, resolved = Path(root).resolve(), joined.resolve()
    else:
      resolved_root = Path(os.path.abspath(root))
      resolved = Path(os.path.normpath(os.path.abspath(joined)))
  except (OSError, RuntimeError) as error:  # RuntimeError: a symlink loop (Python < 3.13).
    raise InputError(f"{text!r} cannot be resolved ({error})", source, field) from None
  if not resolved.is_relative_to(resolved_root):
    raise InputError(f"{text!r} points outside the folder {resolved_root} (to {resolved}); every "
                     "file a data file names must lie inside its folder", source, field)
  return joined


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
  """Writes `data` to `path` atomically: a reader sees the old file or the new, never a part."""
  with atomic_path(path) as temporary:
    temporary.write_bytes(data)


def write_text(path: str | os.PathLike, text: str) -> None:
  """Writes `text` to `path` as UTF-8, atomically."""
  write_bytes(path, text.encode("utf-8"))


def write_json(path: str | os.PathLike, value: Any) -> None:
  """Writes `value` to `path` as indented JSON, atomically; numpy arrays, numpy scalars and paths
  are converted."""
  write_text(path, json.dumps(value, indent=2, default=_json_default) + "\n")


def _json_default(value: Any) -> Any:
  if isinstance(value, np.ndarray):
    return value.tolist()
  if isinstance(value, np.generic):
    return value.item()
  if isinstance(value, Path):
    return str(value)
  raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def read_json(path: str | os.PathLike) -> dict[str, Any]:
  """Parses a JSON file holding an object (every JSON file the project reads does); a missing
  or malformed file, or one holding anything else (`[]`), is an InputError naming it."""
  path = Path(path)
  if not path.is_file():
    raise InputError("file not found", path)
  try:
    value = json.loads(path.read_text(encoding="utf-8"))
  except (json.JSONDecodeError, UnicodeDecodeError) as error:
    raise InputError(f"not valid JSON ({error})", path) from None
  if not isinstance(value, dict):
    raise InputError(f"expected a JSON object {{...}}, found a {type(value).__name__}", path)
  return value


# Larger images are refused before decoding (a 100 megapixel RGBA image is 1.6 GB as float32):
# a few bytes of header can otherwise make the decoder allocate gigabytes.
MAX_IMAGE_PIXELS = 100_000_000
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
JPEG_START = b"\xff\xd8"
# JPEG start-of-frame markers (baseline, progressive, lossless, ...) hold the image size.
JPEG_FRAME_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def _png_size(data: bytes, path: Path) -> tuple[int, int]:
  """(width, height) from the IHDR chunk; the file must end with its IEND chunk."""
  if len(data) < 24 or data[12:16] != b"IHDR":
    raise InputError("not a readable image (PNG without an IHDR header)", path)
  if b"IEND" not in data[-12:]:
    raise InputError("truncated image (the PNG's IEND chunk is missing)", path)
  return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def _jpeg_size(data: bytes, path: Path) -> tuple[int, int]:
  """(width, height) from the first start-of-frame segment; the scan data must be followed by
  the end-of-image marker (a truncated JPEG otherwise decodes with grey where data is missing)."""
  position = 2
  while position + 4 <= len(data):
    if data[position] != 0xFF:
      break
    marker = data[position + 1]
    if marker == 0xFF:  # Fill byte.
      position += 1
      continue
    length = int.from_bytes(data[position + 2:position + 4], "big")
    if marker in JPEG_FRAME_MARKERS and position + 9 <= len(data):
      height = int.from_bytes(data[position + 5:position + 7], "big")
      width = int.from_bytes(data[position + 7:position + 9], "big")
      if data.rfind(b"\xff\xd9") < position:
        raise InputError("truncated image (the JPEG's end-of-image marker is missing)", path)
      return width, height
    position += 2 + length
  raise InputError("not a readable image (JPEG without a frame header, or truncated)", path)


def checked_size(data: bytes, path: Path) -> tuple[int, int] | None:
  """(width, height) of a PNG or JPEG read from its header alone, after checking the file is
  complete; None for other formats (left to the decoder)."""
  if data.startswith(PNG_SIGNATURE):
    size = _png_size(data, path)
  elif data.startswith(JPEG_START):
    size = _jpeg_size(data, path)
  else:
    return None
  if size[0] * size[1] > MAX_IMAGE_PIXELS:
    raise InputError(f"{size[0]}x{size[1]} pixels is more than the {MAX_IMAGE_PIXELS:,} an image "
                     "may have here", path)
  return size


def read_image(path: str | os.PathLike) -> np.ndarray:
  """Reads an 8- or 16-bit PNG/JPEG (other formats OpenCV reads are decoded unchecked).

  Returns:
    [H, W, C] float32 in [0, 1], channels RGB or RGBA (C = 3 or 4); grey images get C = 1.
  Raises:
    InputError: a missing, unreadable, truncated or (PNG/JPEG) oversized file, the size read
      from its header before anything is decoded.
  """
  path = Path(path)
  if not path.is_file():
    raise InputError("image file not found", path)
  data = path.read_bytes()
  if not data:
    raise InputError("not a readable image (the file is empty)", path)
  size = checked_size(data, path)
  image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
  if image is None or (size is not None and image.shape[1::-1] != size):
    raise InputError("not a readable image", path)
  scale = np.float32(np.iinfo(image.dtype).max) if image.dtype.kind in "ui" else np.float32(1)
  image = image.astype(np.float32) / scale
  if image.ndim == 2:
    return image[..., None]
  if image.shape[-1] == 3:
    return image[..., ::-1].copy()
  return image[..., [2, 1, 0, 3]].copy()


def write_image(path: str | os.PathLike, image: np.ndarray, bit_depth: int = 8) -> None:
  """Writes an image atomically.

  Args:
    path: .png or .jpg target.
    image: [H, W], [H, W, 1], [H, W, 3] (RGB) or [H, W, 4] (RGBA), float in [0, 1].
    bit_depth: 8 or 16 (16 only for PNG).
  """
  image = np.asarray(image, np.float32)
  if image.ndim == 3 and image.shape[-1] == 1:
    image = image[..., 0]
  if image.ndim == 3:
    order = [2, 1, 0] if image.shape[-1] == 3 else [2, 1, 0, 3]
    image = image[..., order]
  dtype = {8: np.uint8, 16: np.uint16}[bit_depth]
  quantised = np.round(np.clip(np.nan_to_num(image), 0, 1) * np.iinfo(dtype).max).astype(dtype)
  ok, encoded = cv2.imencode(Path(path).suffix or ".png", quantised)
  if not ok:
    raise InputError("OpenCV could not encode this image type", path)
  write_bytes(path, encoded.tobytes())


def write_exr(path: str | os.PathLike, array: np.ndarray) -> None:
  """Writes a float32 EXR (ZIP compressed): [H, W] as channel Z, [H, W, 3] as RGB."""
  import OpenEXR  # pylint: disable=g-import-not-at-top  (heavy, only needed here)

  array = np.ascontiguousarray(array, np.float32)
  channels = {"Z": array} if array.ndim == 2 else {"RGB": array}
  header = {"type": OpenEXR.scanlineimage, "compression": OpenEXR.ZIP_COMPRESSION}
  with atomic_path(path) as temporary:
    OpenEXR.File(header, channels).write(str(temporary))


def read_exr(path: str | os.PathLike) -> np.ndarray:
  """Reads a single-channel (Z, Y, R or depth) or RGB EXR as float32 [H, W] or [H, W, 3]."""
  import OpenEXR  # pylint: disable=g-import-not-at-top

  path = Path(path)
  if not path.is_file():
    raise InputError("EXR file not found", path)
  try:
    channels = OpenEXR.File(str(path)).channels()
  except Exception as error:  # OpenEXR raises bare exceptions on corrupt files.
    raise InputError(f"not a readable EXR file ({error})", path) from None
  for name in ("Z", "depth", "Y", "R", "RGB", "RGBA"):
    if name in channels:
      pixels = np.asarray(channels[name].pixels, np.float32)
      return pixels[..., :3] if pixels.ndim == 3 else pixels
  if len(channels) == 1:
    return np.asarray(next(iter(channels.values())).pixels, np.float32)
  raise InputError(f"no depth channel among {sorted(channels)}", path, "channels")
