"""NeRF's Blender scenes: `transforms_{train,val,test}.json` and RGBA PNGs (transparent background).

Poses are OpenGL camera-to-world with the object near the origin inside [-1.5, 1.5]^3 (the box
nerfstudio's Blender reader uses), so the normalisation is that box scaled onto [-1, 1]^3. The
focal length follows from `camera_angle_x`, the horizontal field of view, and the image width.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from signerf_jax import files
from signerf_jax.camera import Cameras
from signerf_jax.data import poses as poses_lib
from signerf_jax.data import views
from signerf_jax.data.dataset import Dataset
from signerf_jax.errors import InputError

SCENE_HALF_EXTENT = 1.5
# Evaluation uses NeRF's test split; val is the tuning split the original authors kept apart.
SPLIT_FILES = {"train": ("train",), "eval": ("test",), "all": ("train", "test")}
MISSING_FILES_LISTED = 10


def read_blender(root: str | os.PathLike, *, split: str = "train", downscale: int = 1,
                 background_color=(1.0, 1.0, 1.0)) -> Dataset:
  """Reads a Blender scene into a normalised "bounded" Dataset.

  Args:
    root: the directory holding transforms_{split}.json.
    split: "train" (transforms_train.json), "eval" (transforms_test.json) or "all" (both).
    downscale: integer image downscale (area resampling).
    background_color: [3] RGB the RGBA images are composited on.
  Frames whose image is missing are an error in the train split and skipped with one warning
  naming them in the others (public copies often ship only some test images).
  """
  if split not in SPLIT_FILES:
    raise InputError(f"must be one of {tuple(SPLIT_FILES)}, got {split!r}", field="split")
  root = Path(root)
  image_paths, names, camera_to_world, angles = [], [], [], []
  for split_name in SPLIT_FILES[split]:
    path = root / f"transforms_{split_name}.json"
    meta = files.read_json(path)
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not isinstance(frames, list) or not frames:
      raise InputError("missing or empty (a non-empty list of frames is required)", path,
                       "frames")
    angle = meta.get("camera_angle_x")
    if isinstance(angle, bool) or not isinstance(angle, (int, float)) or not 0 < angle < np.pi:
      raise InputError(f"must be a horizontal field of view in (0, pi) radians, got {angle!r}",
                       path, "camera_angle_x")
    missing = []
    for index, frame in enumerate(frames):
      field = f"frames[{index}]"
      if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
        raise InputError("missing (the image's path is required)", path, f"{field}.file_path")
      relative = Path(frame["file_path"])
      relative = relative if relative.suffix else relative.with_suffix(".png")
      if not (root / relative).is_file():
        if split_name == "train":
          raise InputError(f"image file not found: {root / relative}", path,
                           f"{field}.file_path")
        missing.append(relative.as_posix())
        continue
      if "transform_matrix" not in frame:
        raise InputError("missing", path, f"{field}.transform_matrix")
      camera_to_world.append(poses_lib.check_camera_to_world(
          frame["transform_matrix"], path, f"{field}.transform_matrix"))
      image_paths.append((root / relative, f"{path.name}: {field}.file_path"))
      names.append(relative.as_posix())
      angles.append(angle)
    if missing:
      listed = ", ".join(missing[:MISSING_FILES_LISTED])
      more = f" and {len(missing) - MISSING_FILES_LISTED} more" if len(
          missing) > MISSING_FILES_LISTED else ""
      warnings.warn(f"{path}: skipped {len(missing)} frames whose images are missing: "
                    f"{listed}{more}", stacklevel=3)
  if not names:
    raise InputError(f"no frame of split {split!r} has its image", root)

  height, width = files.read_image(image_paths[0][0]).shape[:2]
  focal = 0.5 * width / np.tan(0.5 * np.asarray(angles))
  cameras = Cameras.create(np.stack(camera_to_world), fx=focal, width=width, height=height)
  world_from_source = poses_lib.similarity(1.0 / SCENE_HALF_EXTENT)
  cameras = poses_lib.transform_cameras(world_from_source, cameras).downscaled(downscale)
  images = np.stack([
      views.read_view(lambda p: views.read_color(p, background_color), image_path, field,
                      file_size=(width, height), target_size=(cameras.width, cameras.height),
                      method="area")
      for image_path, field in image_paths])
  bounds = np.array([[-1, -1, -1], [1, 1, 1]], np.float32)
  near, far = poses_lib.near_far_for_box(cameras, *bounds)
  return Dataset(images=images, cameras=cameras, image_names=tuple(names), scene_bounds=bounds,
                 scene_kind="bounded", near=near, far=far,
                 background_color=np.asarray(background_color, np.float32),
                 world_from_source=world_from_source.astype(np.float32), root=str(root))
