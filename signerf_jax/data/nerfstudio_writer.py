"""Writes a `Dataset` as a nerfstudio dataset (the format: `nerfstudio`'s module docstring).

Layout: images/frame_00000.png (RGB), masks/*.png (if `dataset.masks`), depths/*.exr (z-depth,
if `dataset.depths`), object_masks/*.png (if `dataset.extras["object_masks"]`), and
transforms.json with shared intrinsics (per-frame when they differ), the simplest camera model
that holds the lens (PINHOLE, OPENCV, OPENCV_FISHEYE, or FULL_OPENCV), `applied_transform` =
`dataset.world_from_source` (so the original frame is not lost) and the signerf block (kind,
bounds, background, near/far, provenance when given). Poses are written in the dataset's
normalised frame, so `nerfstudio.read_capture` keeps that frame as it is.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from signerf_jax import files, ownership
from signerf_jax.camera import Cameras
from signerf_jax.data import views
from signerf_jax.data.dataset import Dataset
from signerf_jax.data.nerfstudio import DISTORTION_SLOTS, EXTENSION_KEY, TRANSFORMS_NAME

# OpenCV's rational terms (k4, k5, k6): only FULL_OPENCV holds them.
RATIONAL_SLOTS = slice(5, 8)
# The writer's per-view files: subfolder and suffix per kind of data.
IMAGE_FOLDER, MASK_FOLDER, DEPTH_FOLDER, OBJECT_MASK_FOLDER = (
    "images", "masks", "depths", "object_masks")


def write_nerfstudio(directory: str | os.PathLike, dataset: Dataset, *,
                     provenance: dict[str, Any] | None = None) -> Path:
  """Writes `dataset` in nerfstudio format (see the module docstring); returns the json path.

  Every file is written atomically. An existing transforms.json is removed first and the new one
  is written last, so an interrupted run leaves no transforms.json that points at a mix of old
  and new files; the files of an earlier, larger dataset that the project recorded writing
  (`ownership`) are removed at the end.
  """
  directory = Path(directory)
  directory.mkdir(parents=True, exist_ok=True)
  transforms_path = directory / TRANSFORMS_NAME
  ownership.remove_file(transforms_path)

  cameras = dataset.cameras
  camera_model = _camera_model(cameras)
  intrinsics, shared = _intrinsics(cameras, camera_model)
  frames = []
  for index in range(dataset.num_images):
    frame_intrinsics = {key: values[index] for key, values in intrinsics.items()
                        if key not in shared}
    frames.append(_write_frame(directory, dataset, index, frame_intrinsics))
  meta = {
      "camera_model": camera_model,
      "w": cameras.width,
      "h": cameras.height,
      **shared,
      "applied_transform": np.asarray(dataset.world_from_source, np.float64)[:3].tolist(),
      EXTENSION_KEY: _signerf_block(dataset, provenance),
      "frames": frames,
  }
  files.write_json(transforms_path, meta)
  written = {value for frame in frames for key, value in frame.items() if key.endswith("_path")}
  _remove_stale_frame_files(directory, written)
  return transforms_path


def _camera_model(cameras: Cameras) -> str:
  """The simplest camera model that holds the cameras' lens exactly."""
  distortion = np.asarray(cameras.distortion)
  if cameras.fisheye:
    return "OPENCV_FISHEYE"
  if np.any(distortion[:, RATIONAL_SLOTS] != 0):
    return "FULL_OPENCV"
  return "OPENCV" if np.any(distortion != 0) else "PINHOLE"


def _intrinsics(cameras: Cameras, camera_model: str
                ) -> tuple[dict[str, list[float]], dict[str, float]]:
  """The json's intrinsic keys (`fl_x fl_y cx cy` and the model's coefficients), each as a list
  over the views, and those every view shares (written once, at the top level)."""
  distortion = np.asarray(cameras.distortion)
  intrinsics = {"fl_x": cameras.fx, "fl_y": cameras.fy, "cx": cameras.cx, "cy": cameras.cy}
  intrinsics.update({key: distortion[:, slot]
                     for key, slot in DISTORTION_SLOTS[camera_model].items()})
  intrinsics = {key: np.asarray(values).tolist() for key, values in intrinsics.items()}
  shared = {key: values[0] for key, values in intrinsics.items()
            if all(value == values[0] for value in values)}
  return intrinsics, shared


def _write_frame(directory: Path, dataset: Dataset, index: int,
                 frame_intrinsics: dict[str, float]) -> dict[str, Any]:
  """Writes view `index`'s files (image, and its mask, depth and object ids where the dataset
  has them); returns its `frames` entry, holding `frame_intrinsics` (those views differ in)."""
  name = f"frame_{index:05d}"
  camera_to_world = np.concatenate(
      [np.asarray(dataset.cameras.camera_to_world[index], np.float64), [[0.0, 0.0, 0.0, 1.0]]])
  frame = {"file_path": f"{IMAGE_FOLDER}/{name}.png", "transform_matrix": camera_to_world.tolist()}
  frame.update(frame_intrinsics)
  files.write_image(directory / frame["file_path"], dataset.images[index])
  if dataset.masks is not None:
    frame["mask_path"] = f"{MASK_FOLDER}/{name}.png"
    files.write_image(directory / frame["mask_path"], dataset.masks[index])
  if dataset.depths is not None:
    frame["depth_file_path"] = f"{DEPTH_FOLDER}/{name}.exr"
    files.write_exr(directory / frame["depth_file_path"], dataset.depths[index])
  object_masks = dataset.extras.get("object_masks")
  if object_masks is not None:
    frame["object_mask_path"] = f"{OBJECT_MASK_FOLDER}/{name}.png"
    views.write_object_ids(directory / frame["object_mask_path"], object_masks[index])
  return frame


def _signerf_block(dataset: Dataset, provenance: dict[str, Any] | None) -> dict[str, Any]:
  """The signerf block: the scene frame's kind, bounds, background and near/far, and
  `provenance` when given."""
  extension = {
      "scene_kind": dataset.scene_kind,
      "scene_bounds": np.asarray(dataset.scene_bounds, np.float64).tolist(),
      "background_color": (None if dataset.background_color is None
                           else np.asarray(dataset.background_color, np.float64).tolist()),
      "near": float(dataset.near),
      "far": float(dataset.far),
  }
  if provenance is not None:
    extension["provenance"] = provenance
  return extension


def _remove_stale_frame_files(directory: Path, keep: set[str]) -> None:
  """Deletes the per-view files an earlier write recorded (`ownership`) that the new
  transforms.json no longer lists."""
  for folder in (IMAGE_FOLDER, MASK_FOLDER, DEPTH_FOLDER, OBJECT_MASK_FOLDER):
    for path in ownership.written_files(directory / folder):
      if path.relative_to(directory).as_posix() not in keep:
        ownership.remove_file(path)
