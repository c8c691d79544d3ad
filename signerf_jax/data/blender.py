"""NeRF's Blender scenes: `transforms_{train,val,test}.json` and RGBA PNGs (transparent background).

Poses are OpenGL camera-to-world with the object near the origin inside [-1.5, 1.5]^3 (the box
nerfstudio's Blender reader uses), so the normalisation is that box scaled onto [-1, 1]^3. The
focal length follows from `camera_angle_x`, the horizontal field of view, and the image width.
The train file is the training split and the test file the held-out split (val is the tuning
split the original authors kept apart).
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from signerf_jax import files
from signerf_jax.camera import Cameras
from signerf_jax.data import poses as poses_lib
from signerf_jax.data.capture import Capture, ViewFiles
from signerf_jax.data.frame import SceneFrame
from signerf_jax.errors import InputError

SCENE_HALF_EXTENT = 1.5
MISSING_FILES_LISTED = 10
TEST_FILE_NAME = "transforms_test.json"


def read_capture(root: str | os.PathLike) -> Capture:
  """Reads a Blender scene: transforms_train.json (the train split) and transforms_test.json
  (the held-out split), in a fixed "bounded" frame.

  Frames whose image is missing are an error in the train file and skipped with one warning
  naming them in the test file (public copies often ship only some test images).

  Raises:
    InputError naming the file and entry: a bad field, a missing train image, a path outside
      `root`, or an image listed twice (in one file, or in both).
  """
  root = Path(root)
  view_files, names, camera_to_world, angles = [], [], [], []
  source_splits: dict[str, tuple[int, ...]] = {}
  listed: dict[str, str] = {}  # image name -> the entry that listed it first, for errors
  for split, split_name in (("train", "train"), ("eval", "test")):
    path = root / f"transforms_{split_name}.json"
    if split == "eval" and not path.is_file():
      source_splits[split] = ()
      continue
    split_files, split_names, split_poses, angle, fields = _read_transforms_file(
        root, path, skip_missing=split_name == "test")
    for name, field in zip(split_names, fields):
      if name in listed:
        raise InputError(f"{name!r} is listed again: {listed[name]} names the same image (a "
                         "view is listed once; a training view cannot be held out too)",
                         path, field)
      listed[name] = f"{path.name}'s {field}"
    source_splits[split] = tuple(range(len(names), len(names) + len(split_names)))
    view_files += split_files
    names += split_names
    camera_to_world += split_poses
    angles += [angle] * len(split_names)

  height, width = files.read_image(view_files[0].image).shape[:2]
  focal = 0.5 * width / np.tan(0.5 * np.asarray(angles))
  cameras = Cameras.create(np.stack(camera_to_world), fx=focal, width=width, height=height)
  world_from_source = poses_lib.similarity(1.0 / SCENE_HALF_EXTENT)
  bounds = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
  near, far = poses_lib.near_far_for_box(
      poses_lib.transform_cameras(world_from_source, cameras), *bounds)
  frame = SceneFrame("bounded", world_from_source, bounds, near, far,
                     f"Blender's [-{SCENE_HALF_EXTENT}, {SCENE_HALF_EXTENT}]^3 box")
  return Capture(root=root, cameras=cameras, names=tuple(names), files=tuple(view_files),
                 source_splits=source_splits, frame=frame, kind="bounded", format="blender")


def _read_transforms_file(root: Path, path: Path, skip_missing: bool
                          ) -> tuple[list[ViewFiles], list[str], list[np.ndarray], float,
                                     list[str]]:
  """One split's file: its views' files, names and [3, 4] camera-to-world poses, its
  horizontal field of view (radians), and the field naming each view's image (for errors).

  A frame whose image is missing is an error, or, with `skip_missing`, left out and named in
  one warning.
  """
  meta = files.read_json(path)
  frames = meta.get("frames") if isinstance(meta, dict) else None
  if not isinstance(frames, list) or not frames:
    raise InputError("missing or empty (a non-empty list of frames is required)", path, "frames")
  angle = meta.get("camera_angle_x")
  if isinstance(angle, bool) or not isinstance(angle, (int, float)) or not 0 < angle < np.pi:
    raise InputError(f"must be a horizontal field of view in (0, pi) radians, got {angle!r}",
                     path, "camera_angle_x")
  view_files, names, camera_to_world, missing, fields = [], [], [], [], []
  for index, frame in enumerate(frames):
    field = f"frames[{index}]"
    if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
      raise InputError("missing (the image's path is required)", path, f"{field}.file_path")
    # Refuses an empty path or one outside `root` before it is taken apart.
    files.contained_path(root, frame["file_path"], path, f"{field}.file_path")
    relative = Path(frame["file_path"])
    if relative.name in ("", ".", ".."):
      raise InputError(f"{frame['file_path']!r} names a folder, not an image", path,
                       f"{field}.file_path")
    relative = relative if relative.suffix else relative.with_suffix(".png")
    # With ".png" added, the name may be a symlink leading out where the name without it did not.
    image = files.contained_path(root, relative, path, f"{field}.file_path")
    if not image.is_file():
      if not skip_missing:
        raise InputError(f"image file not found: {image}", path, f"{field}.file_path")
      missing.append(relative.as_posix())
      continue
    if "transform_matrix" not in frame:
      raise InputError("missing", path, f"{field}.transform_matrix")
    camera_to_world.append(poses_lib.check_camera_to_world(
        frame["transform_matrix"], path, f"{field}.transform_matrix"))
    view_files.append(ViewFiles(image=image, label=f"{path.name}: {field}"))
    names.append(relative.as_posix())
    fields.append(f"{field}.file_path")
  if missing:
    listed = ", ".join(missing[:MISSING_FILES_LISTED])
    more = f" and {len(missing) - MISSING_FILES_LISTED} more" if len(
        missing) > MISSING_FILES_LISTED else ""
    # Level 4 is load.load_dataset (through read_capture and load.read_capture): the warning
    # names the user's call.
    warnings.warn(f"{path}: skipped {len(missing)} frames whose images are missing: "
                  f"{listed}{more}", stacklevel=4)
  return view_files, names, camera_to_world, angle, fields


def empty_test_split(root: str | os.PathLike) -> InputError:
  """The error for a held-out split that holds no view when the scene's own split is used:
  transforms_test.json is missing, or every image it lists is (`read_capture` skips missing test
  images)."""
  path = Path(root) / TEST_FILE_NAME
  remedy = "add them, or hold out every N-th training view instead with --eval_every N"
  if not path.is_file():
    return InputError("file not found: a Blender scene's held-out views are the test split it "
                      f"lists, so there is no view to evaluate on; {remedy.replace('them', 'it')}",
                      path)
  frames = files.read_json(path).get("frames") or []
  listed = ", ".join(str(frame.get("file_path")) for frame in frames[:3]
                     if isinstance(frame, dict))
  return InputError(f"the test split's images are all missing (none of the {len(frames)} "
                    f"frames' images exists, e.g. {listed}), so there is no view to evaluate on; "
                    f"{remedy}", path, "frames")
