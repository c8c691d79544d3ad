"""nerfstudio `transforms.json`: reader and writer.

The format (https://docs.nerf.studio/quickstart/data_conventions.html): OpenGL camera-to-world
`transform_matrix` per frame, intrinsics `fl_x fl_y cx cy w h` and OpenCV distortion `k1 k2 p1 p2`
at the top level or per frame (per-frame values win), `camera_model` OPENCV or PINHOLE,
per-frame `file_path`, `mask_path` (0 = ignore the pixel) and `depth_file_path` (z-depth: EXR as
stored, 16-bit PNG times `depth_unit_scale_factor`, default 1e-3), and `applied_transform` (3x4:
the file's poses = applied_transform @ the poses in the capture's original frame).

signerf extension (optional, ignored by nerfstudio): a top-level block
  "signerf": {"scene_kind": "bounded" | "forward_facing" | "unbounded",
              "scene_bounds": [[x, y, z], [x, y, z]],   # in the file's frame
              "background_color": [r, g, b] | null, "near": float, "far": float,
              "provenance": {...}}                      # free-form, written by our tools
and per frame "object_mask_path": an 8-bit PNG of object ids (0 = none), loaded into
`Dataset.extras["object_masks"]`.

Normalisation into the scene frame (content inside [-1, 1]^3):
  * with `signerf.scene_bounds`: bounds already inside [-1, 1]^3 are kept as they are (the file is
    already normalised, e.g. written by `write_nerfstudio`); others are centred and scaled so
    their largest side spans [-1, 1]. near/far default to the range covering the bounds.
  * without it (a plain nerfstudio capture), as nerfstudio's defaults do: rotate the mean camera
    up vector onto +z, centre the camera positions on their mean and scale them into [-1, 1]^3.
    The scene is "forward_facing" when every camera looks within 45 degrees of the mean viewing
    direction and "unbounded" otherwise; bounds are [-1, 1]^3, near/far are nerfacto's 0.05/1000.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from signerf_jax import files
from signerf_jax.camera import Cameras
from signerf_jax.data import poses as poses_lib
from signerf_jax.data import views
from signerf_jax.data.dataset import SCENE_KINDS, Dataset
from signerf_jax.errors import InputError

TRANSFORMS_NAME = "transforms.json"
EXTENSION_KEY = "signerf"
DISTORTION_KEYS = ("k1", "k2", "p1", "p2")
# Radial terms our camera model does not have: a file using them cannot be read faithfully.
UNSUPPORTED_DISTORTION_KEYS = ("k3", "k4")
CAMERA_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")
DEFAULT_DEPTH_UNIT_SCALE = 1e-3
# nerfacto's ray range for captures whose extent is unknown.
UNBOUNDED_NEAR, UNBOUNDED_FAR = 0.05, 1000.0
FORWARD_FACING_MAX_ANGLE_DEGREES = 45.0
# The writer's per-view files: subfolder and suffix per kind of data.
IMAGE_FOLDER, MASK_FOLDER, DEPTH_FOLDER, OBJECT_MASK_FOLDER = (
    "images", "masks", "depths", "object_masks")
_WRITTEN_FILE_PATTERN = re.compile(r"frame_\d{5}\.(png|exr)")


def read_nerfstudio(root: str | os.PathLike, *, split: str = "train", downscale: int = 1,
                    background_color=(1.0, 1.0, 1.0), eval_every: int = 8) -> Dataset:
  """Reads `root`/transforms.json into a normalised Dataset.

  Args:
    root: the dataset directory; file paths in the json are relative to it.
    split: "train", "eval" (every `eval_every`-th frame, starting with the first) or "all".
    downscale: integer image downscale; `images_N/` style copies are used when present.
    background_color: [3] colour RGBA images are composited on (the extension block's colour,
      when given, takes precedence: it is the colour the scene was made with).
    eval_every: the hold-out period of the split.
  Raises:
    InputError: naming the file and field at fault (e.g. `frames[3].transform_matrix`).
  """
  root = Path(root)
  path = root / TRANSFORMS_NAME
  meta = files.read_json(path)
  if not isinstance(meta, dict):
    raise InputError("must hold a JSON object", path)
  frames = meta.get("frames")
  if not isinstance(frames, list) or not frames:
    raise InputError("missing or empty (a non-empty list of frames is required)", path, "frames")
  for index, frame in enumerate(frames):
    if not isinstance(frame, dict):
      raise InputError("must be a JSON object", path, f"frames[{index}]")
    if not isinstance(frame.get("file_path"), str):
      raise InputError("missing (the image's path is required)", path,
                       f"frames[{index}].file_path")

  cameras = _read_cameras(meta, frames, path)
  source_from_original = _applied_transform(meta, path)
  extension = _extension_block(meta, path)
  if "scene_bounds" in extension:
    world_from_file, scene = _scene_from_extension(extension, cameras)
  else:
    world_from_file, scene = _scene_from_cameras(cameras)
  scene["scene_kind"] = extension.get("scene_kind", scene["scene_kind"])
  depth_scale = poses_lib.similarity_scale(world_from_file)
  background = np.asarray(extension.get("background_color") or background_color, np.float32)

  selected = views.split_indices(len(frames), split, eval_every)
  full_size = (cameras.width, cameras.height)
  cameras = poses_lib.transform_cameras(world_from_file, cameras).take(selected)
  cameras = cameras.downscaled(downscale)
  target_size = (cameras.width, cameras.height)
  png_depth_scale = meta.get("depth_unit_scale_factor", DEFAULT_DEPTH_UNIT_SCALE)
  if (isinstance(png_depth_scale, bool) or not isinstance(png_depth_scale, (int, float))
      or not 0 < png_depth_scale < math.inf):
    raise InputError(f"must be a finite positive number, got {png_depth_scale!r}", path,
                     "depth_unit_scale_factor")

  def read_all(key, read, method, default):
    """The per-view files named by `key` ([N, H, W(, C)]), or None when no frame has one."""
    if not any(key in frames[index] for index in selected):
      return None
    arrays = []
    for index in selected:
      if key not in frames[index]:
        arrays.append(np.full(target_size[::-1], default, np.float32))
        continue
      relative = frames[index][key]
      prepared = views.prepared_downscale_path(root, relative, downscale)
      arrays.append(views.read_view(
          read, prepared or root / relative, f"frames[{index}].{key}",
          file_size=target_size if prepared else full_size, target_size=target_size,
          method=method, size_tolerance=1 if prepared else 0))
    return np.stack(arrays)

  images = read_all("file_path", lambda p: views.read_color(p, background), "area", 0.0)
  masks = read_all("mask_path", views.read_mask, "area", 1.0)
  depths = read_all("depth_file_path", lambda p: views.read_depth(p, png_depth_scale),
                    "nearest", 0.0)
  object_masks = read_all("object_mask_path", views.read_object_ids, "nearest", 0)
  return Dataset(
      images=images,
      cameras=cameras,
      image_names=tuple(frames[index]["file_path"] for index in selected),
      background_color=background if scene["scene_kind"] == "bounded" else None,
      world_from_source=(world_from_file @ source_from_original).astype(np.float32),
      masks=masks,
      depths=None if depths is None else depths * np.float32(depth_scale),
      extras={} if object_masks is None else {"object_masks": object_masks.astype(np.int32)},
      root=str(root),
      **scene,
  )


def _read_cameras(meta: dict[str, Any], frames: list[dict[str, Any]], path: Path) -> Cameras:
  """All frames' cameras in the file's frame, at the resolution the json declares."""
  camera_model = meta.get("camera_model", "OPENCV")
  if camera_model not in CAMERA_MODELS:
    raise InputError(f"unsupported camera model {camera_model!r} (supported: {CAMERA_MODELS})",
                     path, "camera_model")
  cameras = [_frame_camera(meta, frame, f"frames[{index}]", path, camera_model)
             for index, frame in enumerate(frames)]
  width, height = cameras[0]["size"]
  for index, frame_camera in enumerate(cameras):
    frame_width, frame_height = frame_camera["size"]
    if (frame_width, frame_height) != (width, height):
      raise InputError(f"image size {frame_width}x{frame_height} differs from the first frame's "
                       f"{width}x{height} (images of mixed sizes)", path,
                       f"frames[{index}].{'w' if frame_width != width else 'h'}")
  stacked = {key: np.stack([frame_camera[key] for frame_camera in cameras])
             for key in ("camera_to_world", "fx", "fy", "cx", "cy", "distortion")}
  return Cameras.create(width=width, height=height, **stacked)


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
  for key in UNSUPPORTED_DISTORTION_KEYS:
    if number(key, 0.0) != 0.0:
      raise InputError("is not supported (only k1, k2, p1, p2 distortion)", path, value(key)[1])
  if "transform_matrix" not in frame:
    raise InputError("missing", path, f"{prefix}.transform_matrix")
  return {
      "size": (width, height),
      "fx": fx,
      "fy": focal_length("fl_y", fx),
      "cx": number("cx", width / 2),
      "cy": number("cy", height / 2),
      "distortion": [number(key, 0.0) if camera_model == "OPENCV" else 0.0
                     for key in DISTORTION_KEYS],
      "camera_to_world": poses_lib.check_camera_to_world(
          frame["transform_matrix"], path, f"{prefix}.transform_matrix"),
  }


def _applied_transform(meta: dict[str, Any], path: Path) -> np.ndarray:
  """[4, 4] map from the capture's original frame into the file's frame (identity if absent)."""
  if "applied_transform" not in meta:
    return np.eye(4)
  try:
    matrix = np.asarray(meta["applied_transform"], np.float64)
  except (TypeError, ValueError):
    matrix = None
  if matrix is None or matrix.shape not in ((3, 4), (4, 4)) or not np.all(np.isfinite(matrix)):
    raise InputError("must be a finite 3x4 or 4x4 matrix", path, "applied_transform")
  return np.concatenate([matrix[:3], [[0.0, 0.0, 0.0, 1.0]]])


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


def _scene_from_extension(extension: dict[str, Any],
                          cameras: Cameras) -> tuple[np.ndarray, dict[str, Any]]:
  """The file-to-scene similarity and the scene's kind, bounds, near, far from the signerf block."""
  lower, upper = np.asarray(extension["scene_bounds"], np.float64)
  inside_unit_box = np.all(lower >= -1 - 1e-6) and np.all(upper <= 1 + 1e-6)
  world_from_file = np.eye(4) if inside_unit_box else poses_lib.unit_box_similarity(lower, upper)
  scale = poses_lib.similarity_scale(world_from_file)
  bounds = poses_lib.transform_points(world_from_file, np.stack([lower, upper]))
  if extension.get("near") is not None and extension.get("far") is not None:
    near, far = scale * extension["near"], scale * extension["far"]
  else:
    near, far = poses_lib.near_far_for_box(
        poses_lib.transform_cameras(world_from_file, cameras), *bounds)
  return world_from_file, dict(scene_kind="bounded", scene_bounds=bounds.astype(np.float32),
                               near=float(near), far=float(far))


def _scene_from_cameras(cameras: Cameras) -> tuple[np.ndarray, dict[str, Any]]:
  """nerfstudio's default normalisation (up to +z, centred, cameras in [-1, 1]^3) and the kind."""
  camera_to_world = np.asarray(cameras.camera_to_world, np.float64)
  rotation = poses_lib.rotation_between(camera_to_world[:, :, 1].mean(0), [0.0, 0.0, 1.0])
  positions = camera_to_world[:, :, 3] @ rotation.T
  centre = positions.mean(0)
  scale = 1.0 / max(np.max(np.abs(positions - centre)), 1e-12)
  world_from_file = poses_lib.similarity(scale, rotation, -scale * centre)
  forwards = -camera_to_world[:, :, 2]
  mean_forward = forwards.mean(0) / max(np.linalg.norm(forwards.mean(0)), 1e-12)
  forward_facing = np.min(forwards @ mean_forward) > np.cos(
      np.radians(FORWARD_FACING_MAX_ANGLE_DEGREES))
  return world_from_file, dict(scene_kind="forward_facing" if forward_facing else "unbounded",
                               scene_bounds=np.array([[-1, -1, -1], [1, 1, 1]], np.float32),
                               near=UNBOUNDED_NEAR, far=UNBOUNDED_FAR)


def write_nerfstudio(directory: str | os.PathLike, dataset: Dataset, *,
                     provenance: dict[str, Any] | None = None) -> Path:
  """Writes `dataset` in nerfstudio format (poses in its normalised frame); returns the json path.

  Layout: images/frame_00000.png (RGB), masks/*.png (if `dataset.masks`), depths/*.exr (z-depth,
  if `dataset.depths`), object_masks/*.png (if `dataset.extras["object_masks"]`), and
  transforms.json with shared intrinsics (per-frame when they differ), OpenCV distortion,
  `applied_transform` = `dataset.world_from_source` (so the original frame is not lost) and the
  signerf block (kind, bounds, background, near/far, `provenance` when given).

  Every file is written atomically. An existing transforms.json is removed first and the new one
  is written last, so an interrupted run leaves no transforms.json that points at a mix of old
  and new files; stale `frame_*` files of an earlier, larger dataset are removed at the end.
  """
  directory = Path(directory)
  directory.mkdir(parents=True, exist_ok=True)
  transforms_path = directory / TRANSFORMS_NAME
  transforms_path.unlink(missing_ok=True)

  cameras = dataset.cameras
  intrinsics = {"fl_x": cameras.fx, "fl_y": cameras.fy, "cx": cameras.cx, "cy": cameras.cy}
  intrinsics.update(zip(DISTORTION_KEYS, np.asarray(cameras.distortion).T))
  intrinsics = {key: np.asarray(values).tolist() for key, values in intrinsics.items()}
  shared = {key: values[0] for key, values in intrinsics.items()
            if all(value == values[0] for value in values)}
  has_distortion = bool(np.any(np.asarray(cameras.distortion) != 0))
  object_masks = dataset.extras.get("object_masks")

  written = []
  frames = []
  for index in range(dataset.num_images):
    name = f"frame_{index:05d}"
    camera_to_world = np.concatenate(
        [np.asarray(cameras.camera_to_world[index], np.float64), [[0.0, 0.0, 0.0, 1.0]]])
    frame = {"file_path": f"{IMAGE_FOLDER}/{name}.png",
             "transform_matrix": camera_to_world.tolist()}
    frame.update({key: values[index] for key, values in intrinsics.items()
                  if key not in shared and (has_distortion or key not in DISTORTION_KEYS)})
    files.write_image(directory / frame["file_path"], dataset.images[index])
    if dataset.masks is not None:
      frame["mask_path"] = f"{MASK_FOLDER}/{name}.png"
      files.write_image(directory / frame["mask_path"], dataset.masks[index])
    if dataset.depths is not None:
      frame["depth_file_path"] = f"{DEPTH_FOLDER}/{name}.exr"
      files.write_exr(directory / frame["depth_file_path"], dataset.depths[index])
    if object_masks is not None:
      frame["object_mask_path"] = f"{OBJECT_MASK_FOLDER}/{name}.png"
      views.write_object_ids(directory / frame["object_mask_path"], object_masks[index])
    written += [value for key, value in frame.items() if key.endswith("_path")]
    frames.append(frame)

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
  meta = {
      "camera_model": "OPENCV" if has_distortion else "PINHOLE",
      "w": cameras.width,
      "h": cameras.height,
      **{key: value for key, value in shared.items()
         if has_distortion or key not in DISTORTION_KEYS},
      "applied_transform": np.asarray(dataset.world_from_source, np.float64)[:3].tolist(),
      EXTENSION_KEY: extension,
      "frames": frames,
  }
  files.write_json(transforms_path, meta)
  _remove_stale_frame_files(directory, set(written))
  return transforms_path


def _remove_stale_frame_files(directory: Path, keep: set[str]) -> None:
  """Deletes our own `frame_NNNNN` files that the new transforms.json no longer lists."""
  for folder in (IMAGE_FOLDER, MASK_FOLDER, DEPTH_FOLDER, OBJECT_MASK_FOLDER):
    for path in sorted((directory / folder).glob("frame_*")):
      if _WRITTEN_FILE_PATTERN.fullmatch(path.name) and f"{folder}/{path.name}" not in keep:
        path.unlink()
