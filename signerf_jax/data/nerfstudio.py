"""nerfstudio `transforms.json` (and instant-NGP-style `transforms_{train,val,test}.json`): the
format, and its reader (`nerfstudio_writer` writes it).

The format (https://docs.nerf.studio/quickstart/data_conventions.html): OpenGL camera-to-world
`transform_matrix` per frame, intrinsics `fl_x fl_y cx cy w h` and distortion coefficients at the
top level or per frame (per-frame values win), per-frame `file_path` (a path without extension
is looked up as .png / .jpg), `mask_path` (0 = ignore the pixel), `depth_file_path` (z-depth:
EXR as stored, 16-bit PNG times `depth_unit_scale_factor`, default 1e-3), `applied_transform`
(3x4: the file's poses = applied_transform @ the poses in the capture's original frame) and the
split keys `train_filenames`, `val_filenames`, `test_filenames`. A capture may instead come as
`transforms_train.json` with `transforms_val.json` / `transforms_test.json` that carry their own
intrinsics (`fl_x`; a file with only `camera_angle_x` is a Blender scene): the files are the split.

`camera_model` (top level) names the lens and its coefficients (absent ones are 0):
  * PINHOLE, SIMPLE_PINHOLE: none (coefficients in the file are ignored, as nerfstudio does);
  * OPENCV: `k1 k2 p1 p2 k3`, OpenCV's meaning. nerfstudio's OPENCV also has `k4`, a polynomial
    r^8 term OpenCV's model lacks (OpenCV's k4 divides): a non-zero `k4` is an error;
  * OPENCV_FISHEYE: cv2.fisheye's `k1 k2 k3 k4`;
  * FULL_OPENCV (this project's extension, not read by nerfstudio): OpenCV's rational model,
    `k1 k2 p1 p2 k3 k4 k5 k6`; the writer uses it only for lenses with a non-zero k4, k5 or k6.

signerf extension (optional, ignored by nerfstudio): a top-level block
  "signerf": {"scene_kind": "bounded" | "forward_facing" | "unbounded",
              "scene_bounds": [[x, y, z], [x, y, z]],   # in the file's frame
              "background_color": [r, g, b] | null, "near": float, "far": float,
              "provenance": {...}}                      # free-form, written by our tools
and per frame "object_mask_path": an 8-bit PNG of object ids (0 = none), loaded into
`Dataset.extras["object_masks"]`.

The scene frame: `signerf.scene_bounds` inside [-1, 1]^3 are kept (e.g. `nerfstudio_writer`'s),
others centred and scaled to span [-1, 1]; without them `frame.estimate_frame` finds the frame.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from signerf_jax import files
from signerf_jax.camera import Cameras
from signerf_jax.lens import DISTORTION_SIZE
from signerf_jax.data import poses as poses_lib
from signerf_jax.data import splits
from signerf_jax.data.capture import FILE_KEYS, Capture, ViewFiles
from signerf_jax.data.frame import SCENE_KINDS, SceneFrame
from signerf_jax.errors import InputError

TRANSFORMS_NAME = "transforms.json"
SPLIT_FILE_NAMES = {"train": "transforms_train.json", "val": "transforms_val.json",
                    "test": "transforms_test.json"}
SPLIT_KEYS = {"train": "train_filenames", "val": "val_filenames", "test": "test_filenames"}
EXTENSION_KEY = "signerf"
# Each camera model's distortion keys and their slots in `Cameras.distortion` (OpenCV's order:
# k1, k2, p1, p2, k3, k4, k5, k6; a fisheye's k1, k2, k3, k4).
DISTORTION_SLOTS = {
    "OPENCV": {"k1": 0, "k2": 1, "p1": 2, "p2": 3, "k3": 4},
    "FULL_OPENCV": {"k1": 0, "k2": 1, "p1": 2, "p2": 3, "k3": 4, "k4": 5, "k5": 6, "k6": 7},
    "OPENCV_FISHEYE": {"k1": 0, "k2": 1, "k3": 2, "k4": 3},
    "PINHOLE": {},
    "SIMPLE_PINHOLE": {},
}
CAMERA_MODELS = tuple(DISTORTION_SLOTS)
FISHEYE_MODELS = ("OPENCV_FISHEYE",)
DEFAULT_DEPTH_UNIT_SCALE = 1e-3
# Extensions tried, in order, for a `file_path` given without one (instant-NGP captures).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
# Larger distortion coefficients are refused. They act on normalised image coordinates (r = 1
# at 45 degrees off-axis), where real lenses' coefficients are below 1 (wide-angle k1 ~ -0.3),
# and the rational model's, whose numerator and denominator nearly cancel, a few hundred at
# most; a k1 of 1e3 would move a point at r = 0.5 by 125 focal lengths. Such values are
# corrupt files, not lenses.
MAX_DISTORTION_COEFFICIENT = 1e3
# `signerf.scene_bounds` whose largest side is below this fraction of the farthest camera's
# distance from the box (or of the box's own distance from the origin, if larger) are refused:
# the scene is stored in float32 (7 significant digits), which cannot place a sample inside
# such a box, and the model's grid would get no cell of it.
MIN_BOUNDS_FRACTION = 1e-5


def has_intrinsics(meta: Any) -> bool:
  """Whether a transforms file carries pixel intrinsics (nerfstudio / instant-NGP), not only
  Blender's `camera_angle_x`."""
  if not isinstance(meta, dict):
    return False
  frames = meta.get("frames") if isinstance(meta.get("frames"), list) else []
  return "fl_x" in meta or any(isinstance(frame, dict) and "fl_x" in frame for frame in frames)


def read_capture(root: str | os.PathLike) -> Capture:
  """Reads `root`/transforms.json, or the `transforms_{train,val,test}.json` split files.

  Raises:
    InputError: naming the file and field at fault (e.g. `frames[3].transform_matrix`).
  """
  root = Path(root)
  if (root / TRANSFORMS_NAME).is_file():
    path = root / TRANSFORMS_NAME
    meta = _read_meta(path)
    entries = [(path, meta, index, frame) for index, frame in enumerate(meta["frames"])]
    splits.check_listed_once([(path, f"frames[{index}].file_path", frame["file_path"])
                              for path, _, index, frame in entries])
    names = [frame["file_path"] for _, _, _, frame in entries]
    source_splits = _split_keys(meta, names, path)
  else:
    entries, source_splits = _read_split_files(root)
    meta = _read_meta(root / SPLIT_FILE_NAMES["train"])
    path = root / SPLIT_FILE_NAMES["train"]
    names = [frame["file_path"] for _, _, _, frame in entries]

  cameras = _read_cameras(entries)
  extension = _extension_block(meta, path)
  frame = (_frame_from_extension(extension, cameras, path) if "scene_bounds" in extension
           else None)
  depth_scale = meta.get("depth_unit_scale_factor", DEFAULT_DEPTH_UNIT_SCALE)
  if (isinstance(depth_scale, bool) or not isinstance(depth_scale, (int, float))
      or not 0 < depth_scale < math.inf):
    raise InputError(f"must be a finite positive number, got {depth_scale!r}", path,
                     "depth_unit_scale_factor")
  background = extension.get("background_color")
  return Capture(
      root=root,
      cameras=cameras,
      names=tuple(names),
      files=tuple(_view_files(root, entry, label)
                  for label, entry in zip(_labels(entries, root), entries)),
      source_splits=source_splits,
      frame=frame,
      kind=extension.get("scene_kind"),
      depth_unit_scale=float(depth_scale),
      file_from_source=(poses_lib.check_similarity(meta["applied_transform"], path,
                                                   "applied_transform")
                        if "applied_transform" in meta else np.eye(4)),
      background_color=None if background is None else np.asarray(background, np.float32),
      format="nerfstudio",
  )


def _read_meta(path: Path) -> dict[str, Any]:
  """A transforms file with a validated, non-empty `frames` list (each with a `file_path`)."""
  meta = files.read_json(path)
  frames = meta.get("frames")
  if not isinstance(frames, list) or not frames:
    raise InputError("missing or empty (a non-empty list of frames is required)", path, "frames")
  for index, frame in enumerate(frames):
    if not isinstance(frame, dict):
      raise InputError("must be a JSON object", path, f"frames[{index}]")
    if not isinstance(frame.get("file_path"), str):
      raise InputError("missing (the image's path is required)", path,
                       f"frames[{index}].file_path")
  return meta


def _split_keys(meta: dict[str, Any], names: list[str], path: Path
                ) -> dict[str, tuple[int, ...]] | None:
  """nerfstudio's split keys as view indices: train, and eval = val (nerfstudio's evaluation
  split), else test. None when the file has none."""
  listed = {split: meta[key] for split, key in SPLIT_KEYS.items() if key in meta}
  if not listed:
    return None
  indices = {}
  for split, values in listed.items():
    if not isinstance(values, list) or not all(isinstance(value, str) for value in values):
      raise InputError("must be a list of file paths", path, SPLIT_KEYS[split])
    indices[split] = tuple(splits.match_names(names, values, path, SPLIT_KEYS[split]).tolist())
  if "train" not in indices:
    raise InputError("missing while other split keys are given (nerfstudio requires it)", path,
                     SPLIT_KEYS["train"])
  return {"train": indices["train"], "eval": indices.get("val", indices.get("test", ()))}


def _read_split_files(root: Path):
  """Frames of transforms_{train,val,test}.json, each view once (instant-NGP captures often
  repeat the test frames as val), and the split the files make.

  Raises:
    InputError naming both entries: a file listing an image twice, or a training image listed
    again in the val or test file (it would be evaluated on after being trained on).
  """
  entries, indices_by_name = [], {}
  split_indices: dict[str, list[int]] = {}
  for split, file_name in SPLIT_FILE_NAMES.items():
    path = root / file_name
    if not path.is_file():
      if split == "train":
        raise InputError("file not found", path)
      continue
    meta = _read_meta(path)
    splits.check_listed_once([(path, f"frames[{index}].file_path", frame["file_path"])
                              for index, frame in enumerate(meta["frames"])])
    split_indices[split] = []
    for index, frame in enumerate(meta["frames"]):
      key = splits.name_key(frame["file_path"])
      if key not in indices_by_name:
        indices_by_name[key] = len(entries)
        entries.append((path, meta, index, frame))
      elif split != "train" and indices_by_name[key] in split_indices["train"]:
        first_path, _, first_index, _ = entries[indices_by_name[key]]
        raise InputError(f"{frame['file_path']!r} is also {first_path.name}'s "
                         f"frames[{first_index}]: a view cannot be both trained on and held "
                         "out", path, f"frames[{index}].file_path")
      split_indices[split].append(indices_by_name[key])
  evaluation = split_indices.get("test", split_indices.get("val", []))
  return entries, {"train": tuple(split_indices["train"]), "eval": tuple(evaluation)}


def _image_path(root: Path, relative: str, source: Path, field: str) -> Path:
  """The image a `file_path` names; without an extension, the first of IMAGE_SUFFIXES found.
  Either must lie inside `root` (`files.contained_path`; `source` and `field` name the entry)."""
  path = files.contained_path(root, relative, source, field)
  if path.suffix or path.is_file():
    return path
  for suffix in IMAGE_SUFFIXES:
    candidate = path.with_name(path.name + suffix)
    if candidate.is_file():
      # It may be a symlink out where `path` was not (relative: `root` is in `candidate`).
      return files.contained_path(root, os.path.relpath(candidate, root), source, field)
  return path


def _labels(entries, root: Path) -> list[str]:
  """How errors name each view: "frames[i]", prefixed by the file when there are several."""
  several = len({path for path, _, _, _ in entries}) > 1
  return [f"{path.relative_to(root)}: frames[{index}]" if several else f"frames[{index}]"
          for path, _, index, _ in entries]


def _view_files(root: Path, entry, label: str) -> ViewFiles:
  """One frame's files, each checked to lie inside `root`.

  Args:
    entry: (path, meta, index, frame): the transforms file, its top level, the frame's index
      there and the frame.
  """
  path, _, index, frame = entry
  field = lambda key: f"frames[{index}].{key}"
  others = {}
  for kind, key in FILE_KEYS.items():
    if kind == "image" or frame.get(key) is None:
      continue
    others[kind] = files.contained_path(root, frame[key], path, field(key))
  return ViewFiles(image=_image_path(root, frame["file_path"], path, field("file_path")),
                   label=label, **others)


def _read_cameras(entries) -> Cameras:
  """All frames' cameras in the file's frame, at the resolution the json declares.

  Args:
    entries: (path, meta, index, frame) per view: its file, that file's top level, its index
      there and the frame itself.
  """
  cameras, camera_models = [], []
  for path, meta, index, frame in entries:
    camera_model = meta.get("camera_model", "OPENCV")
    if camera_model not in CAMERA_MODELS:
      raise InputError(f"unsupported camera model {camera_model!r} (supported: "
                       f"{CAMERA_MODELS})", path, "camera_model")
    camera_models.append(camera_model)
    cameras.append(_frame_camera(meta, frame, f"frames[{index}]", path, camera_model))
  width, height = cameras[0]["size"]
  fisheye = camera_models[0] in FISHEYE_MODELS
  for (path, _, index, _), frame_camera, camera_model in zip(entries, cameras, camera_models):
    if (camera_model in FISHEYE_MODELS) != fisheye:
      raise InputError(f"{camera_model} and the first frame's {camera_models[0]} mix fisheye and "
                       "perspective lenses (a dataset has one lens model)", path, "camera_model")
    frame_width, frame_height = frame_camera["size"]
    if (frame_width, frame_height) != (width, height):
      raise InputError(f"image size {frame_width}x{frame_height} differs from the first frame's "
                       f"{width}x{height} (images of mixed sizes)", path,
                       f"frames[{index}].{'w' if frame_width != width else 'h'}")
  stacked = {key: np.stack([frame_camera[key] for frame_camera in cameras])
             for key in ("camera_to_world", "fx", "fy", "cx", "cy", "distortion")}
  return Cameras.create(width=width, height=height, fisheye=fisheye, **stacked)


def _frame_camera(meta: dict[str, Any], frame: dict[str, Any], prefix: str, path: Path,
                  camera_model: str) -> dict[str, Any]:
  """One frame's validated camera: intrinsics from the frame, else from the top level."""

  def value(key, default=None):
    """The raw value and the field it came from."""
    if key in frame:
      return frame[key], f"{prefix}.{key}"
    if key in meta:
      return meta[key], key
    if default is None:
      raise InputError("missing (needed at the top level or in the frame)", path,
                       f"{prefix}.{key}")
    return default, key

  def number(key, default=None):
    raw, field = value(key, default)
    if isinstance(raw, bool) or not isinstance(raw, (int, float)) or not math.isfinite(raw):
      raise InputError(f"must be a finite number, got {raw!r}", path, field)
    return float(raw)

  def coefficient(key):
    raw = number(key, 0.0)
    if abs(raw) > MAX_DISTORTION_COEFFICIENT:
      raise InputError(f"distortion coefficient {raw:g} is no real lens's (their coefficients "
                       f"stay within +-{MAX_DISTORTION_COEFFICIENT:g}); the file is corrupt",
                       path, value(key)[1])
    return raw

  def pixels(key):
    raw, field = value(key)
    if isinstance(raw, bool) or not isinstance(raw, (int, float)) or raw != int(raw) or raw < 1:
      raise InputError(f"must be a positive whole number of pixels, got {raw!r}", path, field)
    return int(raw)

  def focal_length(key, default=None):
    raw, field = value(key, default)
    return poses_lib.check_focal_length(raw, path, field)

  width, height = pixels("w"), pixels("h")
  fx = focal_length("fl_x")
  if camera_model == "OPENCV" and number("k4", 0.0) != 0.0:
    raise InputError("is nerfstudio's polynomial r^8 term of OPENCV, which OpenCV's lens model "
                     "(and this project's) does not have; only 0 can be read", path,
                     value("k4")[1])
  distortion = np.zeros(DISTORTION_SIZE)
  for key, slot in DISTORTION_SLOTS[camera_model].items():
    distortion[slot] = coefficient(key)
  if "transform_matrix" not in frame:
    raise InputError("missing", path, f"{prefix}.transform_matrix")
  return {
      "size": (width, height),
      "fx": fx,
      "fy": focal_length("fl_y", fx),
      "cx": number("cx", width / 2),
      "cy": number("cy", height / 2),
      "distortion": distortion,
      "camera_to_world": poses_lib.check_camera_to_world(
          frame["transform_matrix"], path, f"{prefix}.transform_matrix"),
  }


def _extension_block(meta: dict[str, Any], path: Path) -> dict[str, Any]:
  """The validated signerf block (empty when absent)."""
  block = meta.get(EXTENSION_KEY, {})
  if not isinstance(block, dict):
    raise InputError("must be a JSON object", path, EXTENSION_KEY)
  field = lambda key: f"{EXTENSION_KEY}.{key}"
  if block.get("scene_kind", "bounded") not in SCENE_KINDS:
    raise InputError(f"must be one of {SCENE_KINDS}", path, field("scene_kind"))
  checks = {"scene_bounds": (2, 3), "background_color": (3,), "near": (), "far": ()}
  for key, shape in checks.items():
    if block.get(key) is None:
      continue
    try:
      array = np.asarray(block[key], np.float64)
    except (TypeError, ValueError):
      array = None
    if array is None or array.shape != shape or not np.all(np.isfinite(array)):
      raise InputError(f"must be finite numbers of shape {list(shape)}", path, field(key))
  bounds = block.get("scene_bounds")
  if bounds is not None and not np.all(np.less(bounds[0], bounds[1])):
    raise InputError("min corner must be below max corner on every axis", path,
                     field("scene_bounds"))
  if (block.get("near") is not None and block.get("far") is not None
      and not 0 <= block["near"] < block["far"]):
    raise InputError("need 0 <= near < far", path, field("far"))
  return block


def _frame_from_extension(extension: dict[str, Any], cameras: Cameras, path: Path
                          ) -> SceneFrame:
  """The frame the signerf block fixes: its kind (default bounded), bounds, near and far.

  Raises:
    InputError naming `path` and `signerf.scene_bounds`: bounds too small to hold anything
      (see MIN_BOUNDS_FRACTION).
  """
  lower, upper = np.asarray(extension["scene_bounds"], np.float64)
  largest_side = float(np.max(upper - lower))
  # What the box is measured against: the farthest camera's distance from it and its own
  # distance from the origin (float32 coordinates lose what is smaller than ~1e-7 of either).
  reference = max(float(np.max(np.linalg.norm(
      np.asarray(cameras.positions, np.float64) - (lower + upper) / 2, axis=-1))),
      float(np.max(np.abs([lower, upper]))))
  if not largest_side > MIN_BOUNDS_FRACTION * reference:
    raise InputError(f"the box is degenerate: its largest side {largest_side:.3g} is below "
                     f"{MIN_BOUNDS_FRACTION:g} of the cameras' distance {reference:.3g} (no "
                     "scene fits in it; the bounds are in the file's units)", path,
                     f"{EXTENSION_KEY}.scene_bounds")
  inside_unit_box = np.all(lower >= -1 - 1e-6) and np.all(upper <= 1 + 1e-6)
  world_from_file = np.eye(4) if inside_unit_box else poses_lib.unit_box_similarity(lower, upper)
  scale = poses_lib.similarity_scale(world_from_file)
  bounds = poses_lib.transform_points(world_from_file, np.stack([lower, upper]))
  if extension.get("near") is not None and extension.get("far") is not None:
    near, far = scale * extension["near"], scale * extension["far"]
  else:
    near, far = poses_lib.near_far_for_box(
        poses_lib.transform_cameras(world_from_file, cameras), *bounds)
  return SceneFrame(extension.get("scene_kind", "bounded"), world_from_file, bounds,
                    float(near), float(far), "signerf block")
