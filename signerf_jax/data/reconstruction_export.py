"""A COLMAP reconstruction (pycolmap) as a nerfstudio dataset's transforms.json, and its sparse
model as COLMAP's binary files (the folder layout of nerfstudio's `ns-process-data`)."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from signerf_jax import files
from signerf_jax.data.colmap_bindings import pycolmap
from signerf_jax.data.structure_from_motion import world_from_camera_opengl

# COLMAP's parameter order per camera model -> nerfstudio's keys. SIMPLE_RADIAL's one focal
# length and k1 are written as OPENCV with fl_x = fl_y and k2 = p1 = p2 = 0, which nerfstudio
# and `nerfstudio.read_capture` read.
CAMERA_KEYS = {
    "OPENCV": ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "p1", "p2"),
    "SIMPLE_RADIAL": ("fl_x", "cx", "cy", "k1"),
}


def camera_entry(camera: pycolmap.Camera) -> dict[str, float]:
  """nerfstudio's intrinsic keys (`fl_x fl_y cx cy k1 k2 p1 p2`, pixels) of a COLMAP camera."""
  model = camera.model.name
  if model not in CAMERA_KEYS:
    raise ValueError(f"camera model {model} is not one `signerf process` makes")
  entry = {"fl_x": 0.0, "fl_y": 0.0, "cx": 0.0, "cy": 0.0, "k1": 0.0, "k2": 0.0, "p1": 0.0,
           "p2": 0.0}
  entry.update(dict(zip(CAMERA_KEYS[model], (float(value) for value in camera.params))))
  if model == "SIMPLE_RADIAL":
    entry["fl_y"] = entry["fl_x"]
  return entry


def transforms(model: pycolmap.Reconstruction, image_folder: str,
               provenance: dict[str, Any]) -> dict[str, Any]:
  """transforms.json of the model's registered images, sorted by name: OPENCV intrinsics at the
  top level when every image shares one camera (per frame otherwise), OpenGL camera-to-world
  poses in COLMAP's world frame, and the process's summary as the signerf provenance."""
  images = sorted(model.images.values(), key=lambda image: image.name)
  images = [image for image in images if image.has_pose]
  cameras = {image.camera_id for image in images}
  shared = len(cameras) == 1
  first = model.cameras[images[0].camera_id]
  meta: dict[str, Any] = {"camera_model": "OPENCV", "w": first.width, "h": first.height}
  if shared:
    meta.update(camera_entry(first))
  frames = []
  for image in images:
    frame = {"file_path": f"{image_folder}/{image.name}",
             "transform_matrix": world_from_camera_opengl(image).tolist()}
    if not shared:
      camera = model.cameras[image.camera_id]
      frame.update(camera_entry(camera), w=camera.width, h=camera.height)
    frames.append(frame)
  meta["signerf"] = {"provenance": provenance}
  meta["frames"] = frames
  return meta


def write_sparse_model(model: pycolmap.Reconstruction, directory: Path) -> list[str]:
  """Writes the model's binary files (cameras.bin, images.bin, points3D.bin, ...) into
  `directory`, each atomically; returns their names."""
  with tempfile.TemporaryDirectory(prefix="signerf-model-") as scratch:
    model.write_binary(scratch)
    names = sorted(path.name for path in Path(scratch).iterdir())
    for name in names:
      files.write_bytes(directory / name, (Path(scratch) / name).read_bytes())
  return names


def reprojection_errors(model: pycolmap.Reconstruction) -> np.ndarray:
  """[P] each 3D point's mean reprojection error in pixels."""
  return np.asarray([point.error for point in model.points3D.values()], np.float64)
