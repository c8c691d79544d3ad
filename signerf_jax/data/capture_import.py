"""A capture's images into a dataset folder: a phone's photos (EXIF orientation applied) or the
sharpest frames of a video, and nerfstudio's downscaled copies (images_2/, images_4/,
images_8/), which `load` reads instead of resampling.

Every file is written through `files` (atomic, recorded as the project's); files already
written by an earlier run are kept, so an interrupted import resumes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np

from signerf_jax import files, ownership
from signerf_jax.errors import InputError

IMAGE_FOLDER = "images"
DOWNSCALE_FACTORS = (2, 4, 8)
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp")
# Sharpness is measured on frames scaled to at most this size: the Laplacian's variance ranks
# blur just as well there, and full-HD frames would cost 10x more.
SHARPNESS_SIZE = 480

Progress = Callable[[int], None]


def photo_names(source: Path) -> list[str]:
  """The image files directly in `source`, sorted by name (a phone numbers its photos in the
  order they were taken, which sequential matching uses)."""
  if not source.is_dir():
    raise InputError("not a folder of images", source, "images")
  names = sorted(path.name for path in source.iterdir()
                 if path.is_file() and path.suffix.lower() in PHOTO_SUFFIXES)
  if not names:
    raise InputError(f"holds no images ({', '.join(PHOTO_SUFFIXES)})", source, "images")
  return names


def _output_name(source_name: str) -> str:
  """PNGs stay PNG (lossless in, lossless out); every other format is written as JPEG."""
  stem, suffix = Path(source_name).stem, Path(source_name).suffix.lower()
  return f"{stem}.png" if suffix == ".png" else f"{stem}.jpg"


def import_photos(source: Path, dataset: Path, advance: Progress) -> list[str]:
  """Writes every photo in `source` upright into `dataset/images/`; returns the written names,
  in capture order. Photos an earlier run wrote are kept."""
  names = photo_names(source)
  outputs = [_output_name(name) for name in names]
  if len(set(outputs)) < len(outputs):
    duplicates = sorted({name for name in outputs if outputs.count(name) > 1})
    raise InputError(f"holds images that differ only in their extension ({duplicates[0]} ...): "
                     "rename them", source, "images")
  done = _written_images(dataset)
  for name, output in zip(names, outputs):
    if output not in done:
      files.write_image(dataset / IMAGE_FOLDER / output, read_upright(source / name))
    advance(1)
  return outputs


def read_upright(path: Path) -> np.ndarray:
  """[H, W, 3] float32 RGB in [0, 1] of a photo, turned as its EXIF orientation says (cameras
  store portrait photos sideways with a tag)."""
  data = path.read_bytes()
  # Truncated files and decompression bombs are refused from the header, as `files.read_image`
  # does; IMREAD_COLOR (not its IMREAD_UNCHANGED) applies the EXIF orientation.
  if data:
    files.checked_size(data, path)
  image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR) if data else None
  if image is None:
    raise InputError("not a readable image", path, "images")
  return image[..., ::-1].astype(np.float32) / 255.0


def _written_images(dataset: Path) -> set[str]:
  """Names of the images an earlier run of the project wrote into `dataset/images/`."""
  return {path.name for path in ownership.written_files(dataset / IMAGE_FOLDER)}


def frame_sharpness(video: Path, advance: Progress) -> np.ndarray:
  """[F] variance of the Laplacian of every frame of `video` (higher is sharper)."""
  capture = cv2.VideoCapture(str(video))
  sharpness = []
  try:
    while True:
      ok, frame = capture.read()
      if not ok:
        break
      grey = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
      scale = SHARPNESS_SIZE / max(grey.shape)
      if scale < 1:
        grey = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
      sharpness.append(cv2.Laplacian(grey, cv2.CV_64F).var())
      advance(1)
  finally:
    capture.release()
  if not sharpness:
    raise InputError("not a readable video (no frame could be decoded)", video, "video")
  return np.asarray(sharpness)


def choose_frames(sharpness: np.ndarray, max_frames: int) -> np.ndarray:
  """Indices of the frames kept: the clip cut into `max_frames` equal stretches and the
  sharpest frame of each, so the frames spread over the whole capture and avoid motion blur."""
  count = len(sharpness)
  if count <= max_frames:
    return np.arange(count)
  edges = np.linspace(0, count, max_frames + 1).round().astype(int)
  return np.asarray([start + int(np.argmax(sharpness[start:end]))
                     for start, end in zip(edges[:-1], edges[1:])])


def import_video(video: Path, dataset: Path, max_frames: int, count_frames: Progress,
                 advance: Progress) -> list[str]:
  """Writes the sharpest frames of `video`, spread over the clip (`choose_frames`), into
  `dataset/images/` as frame_<index in the video>.jpg; returns their names in order."""
  if not video.is_file():
    raise InputError("video file not found", video, "video")
  chosen = set(choose_frames(frame_sharpness(video, count_frames), max_frames).tolist())
  names = [f"frame_{index:05d}.jpg" for index in sorted(chosen)]
  done = _written_images(dataset)
  capture = cv2.VideoCapture(str(video))
  try:
    index = 0
    while chosen:
      ok, frame = capture.read()
      if not ok:
        raise InputError(f"ended at frame {index} on a second reading, before frame "
                         f"{min(chosen)}", video, "video")
      if index in chosen:
        chosen.discard(index)
        name = f"frame_{index:05d}.jpg"
        if name not in done:
          files.write_image(dataset / IMAGE_FOLDER / name, frame[..., ::-1] / 255.0)
        advance(1)
      index += 1
  finally:
    capture.release()
  return names


def write_downscaled(dataset: Path, names: Sequence[str], advance: Progress) -> None:
  """images_2/, images_4/, images_8/: each image area-averaged to 1/2, 1/4 and 1/8 of its size
  (sizes rounded down, as `Cameras.downscaled`)."""
  for name in names:
    missing = [factor for factor in DOWNSCALE_FACTORS
               if not (dataset / f"{IMAGE_FOLDER}_{factor}" / name).is_file()]
    if missing:
      image = files.read_image(dataset / IMAGE_FOLDER / name)
      height, width = image.shape[:2]
      for factor in missing:
        size = (max(width // factor, 1), max(height // factor, 1))
        files.write_image(dataset / f"{IMAGE_FOLDER}_{factor}" / name,
                          cv2.resize(image, size, interpolation=cv2.INTER_AREA))
    advance(1)
