"""One entry point for every dataset format: detect it, read it, frame it, split it.

`load_dataset` reads the capture (`Capture`, in the source's frame), finds the scene frame from
all of its views (so every split shares it), picks the split's views and reads only their
pixels, resampled to the requested downscale.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Sequence

import numpy as np

from signerf_jax.data import blender, colmap, llff, nerfstudio, neus, splits, views
from signerf_jax.data import frame as frame_lib
from signerf_jax.data import poses as poses_lib
from signerf_jax.data.capture import FILE_KEYS, Capture, ViewFiles
from signerf_jax.data.dataset import Dataset, SceneViews
from signerf_jax.data.frame import SCENE_KINDS, SceneFrame
from signerf_jax.errors import InputError

FORMATS = ("nerfstudio", "blender", "llff", "colmap", "neus")
# What each format is recognised by, for the error when none is found.
FORMAT_MARKERS = {"nerfstudio": "transforms.json (or transforms_train.json with fl_x)",
                  "blender": "transforms_train.json", "llff": llff.POSES_NAME,
                  "colmap": "sparse/0/cameras.bin with images.bin (or .txt, in sparse/ or here)",
                  "neus": " or ".join(neus.CAMERA_FILE_NAMES)}


def detect_format(root: str | os.PathLike) -> str:
  """The format of the dataset in `root` (one of FORMATS), from the files it holds."""
  root = Path(root)
  if not root.is_dir():
    raise InputError("dataset directory not found", root)
  if (root / nerfstudio.TRANSFORMS_NAME).is_file():
    return "nerfstudio"
  split_file = root / nerfstudio.SPLIT_FILE_NAMES["train"]
  if split_file.is_file():
    # instant-NGP / nerfstudio-style split files carry pixel intrinsics; Blender's only an angle.
    return "nerfstudio" if nerfstudio.has_intrinsics(_json_or_none(split_file)) else "blender"
  if (root / llff.POSES_NAME).is_file():
    return "llff"
  if colmap.model_folder(root) is not None:
    return "colmap"
  if neus.camera_file(root) is not None:
    return "neus"
  raise InputError(f"unknown dataset format: none of {list(FORMAT_MARKERS.values())} found",
                   root)


def _json_or_none(path: Path):
  try:
    return json.loads(path.read_text(encoding="utf-8"))
  except (OSError, ValueError):
    return None  # The reader reports it, naming the file.


def read_capture(root: str | os.PathLike, downscale: int = 1) -> Capture:
  """The capture in `root`, in the source's frame (`downscale` picks LLFF's image folder)."""
  source_format = detect_format(root)
  if source_format == "nerfstudio":
    return nerfstudio.read_capture(root)
  if source_format == "blender":
    return blender.read_capture(root)
  if source_format == "llff":
    return llff.read_capture(root, downscale)
  if source_format == "colmap":
    return colmap.read_capture(root)
  return neus.read_capture(root)


def scene_frame(capture: Capture, *, scene_kind: str | None = None, scene_center=None,
                scene_radius: float | None = None) -> SceneFrame:
  """The capture's scene frame, in the frame its cameras are given in.

  Args:
    capture: the capture.
    scene_kind: overrides the kind the source implies or the cameras suggest. A source that
      fixes its frame (a Blender scene, a signerf-written dataset) keeps its normalisation.
    scene_center, scene_radius: the inner region's centre and half-side in the dataset's own
      units (unbounded scenes), instead of the estimate.
  """
  overrides_region = scene_center is not None or scene_radius is not None
  if capture.frame is not None:
    if overrides_region:
      raise InputError(f"this {capture.format} dataset fixes its own scene frame; scene_center "
                       "and scene_radius apply to captures whose frame is estimated",
                       capture.root, "scene_center")
    return capture.frame if scene_kind is None else dataclasses.replace(capture.frame,
                                                                        kind=scene_kind)
  if scene_center is not None:  # The dataset's units -> the frame its cameras are given in.
    scene_center = poses_lib.transform_points(capture.file_from_source,
                                              _vector(scene_center, "scene_center"))
  if scene_radius is not None:
    scene_radius = float(scene_radius) * poses_lib.similarity_scale(capture.file_from_source)
  kind = scene_kind or capture.kind
  try:
    estimated = frame_lib.estimate_frame(
        capture.cameras, kind="unbounded" if kind == "bounded" else kind, points=capture.points,
        depth_bounds=capture.depth_bounds, object_sphere=capture.object_sphere,
        scene_center=scene_center, scene_radius=scene_radius)
  except InputError as error:
    if error.path is not None or error.field is not None:
      raise
    # A problem of the cameras themselves (they do not move): name the dataset.
    raise InputError(error.problem, capture.root) from None
  if kind != "bounded":
    return estimated
  # A bounded scene: the same inner region, rays confined to it, a constant background.
  cameras = poses_lib.transform_cameras(estimated.world_from_source, capture.cameras)
  near, far = poses_lib.near_far_for_box(cameras, *estimated.bounds)
  return dataclasses.replace(estimated, kind="bounded", near=near, far=far)


def _vector(value, field: str) -> np.ndarray:
  try:
    vector = np.asarray(value, np.float64)
  except (TypeError, ValueError):
    vector = None
  if vector is None or vector.shape != (3,) or not np.all(np.isfinite(vector)):
    raise InputError(f"must be three finite numbers (x, y, z), got {value!r}", field=field)
  return vector


def load_dataset(root: str | os.PathLike, *, split: str = "train", downscale: int = 1,
                 background_color=(1.0, 1.0, 1.0), eval_every: int | None = None,
                 held_out: Sequence[str] = (), scene_kind: str | None = None,
                 scene_center=None, scene_radius: float | None = None) -> Dataset:
  """Reads a dataset into the normalised scene frame.

  Args:
    root: the dataset directory.
    split: "train", "eval" or "all" (see `splits.select_views` for which views are held out).
    downscale: integer image downscale; `images_N/` folders are used where the source has them,
      otherwise images are area-resampled. Intrinsics follow `Cameras.downscaled`.
    background_color: [3] RGB that RGBA images are composited on when the source names none.
    eval_every: hold out every N-th view instead of the source's own split.
    held_out: names of the views to hold out (wins over `eval_every` and the source's split).
    scene_kind, scene_center, scene_radius: overrides of the scene frame (`scene_frame`).
  Returns:
    A Dataset in the scene frame; `world_from_source` maps the source's frame into it and
    `frame` describes it. Every split of one source shares that frame.
  Raises:
    InputError: naming the file and field, or the parameter, at fault.
  """
  capture, frame, selected, scene_views = _chosen_views(
      root, split, downscale, eval_every, held_out, scene_kind, scene_center, scene_radius)
  background = (capture.background_color if capture.background_color is not None
                else np.asarray(background_color, np.float32))
  cameras = scene_views.cameras
  reader = _ViewReader(capture, downscale, (cameras.width, cameras.height))
  chosen_files = [capture.files[index] for index in selected]
  images, alphas, masks, depths, object_masks = reader.read_views(chosen_files, background)
  if masks is not None and not np.any(masks > 0):
    raise _no_unmasked_pixel(capture, chosen_files, split)
  return Dataset(
      images=images,
      cameras=cameras,
      image_names=scene_views.image_names,
      scene_bounds=scene_views.scene_bounds,
      scene_kind=scene_views.scene_kind,
      near=float(frame.near),
      far=float(frame.far),
      background_color=background if frame.kind == "bounded" else None,
      world_from_source=scene_views.world_from_source,
      alphas=alphas if np.any(alphas < 1) else None,
      masks=masks,
      depths=None if depths is None else depths * np.float32(frame.scale),
      extras={} if object_masks is None else {"object_masks": object_masks.astype(np.int32)},
      root=str(root),
      frame=dataclasses.replace(frame, world_from_source=frame.world_from_source
                                @ capture.file_from_source).describe(),
  )


def _no_unmasked_pixel(capture: Capture, chosen: Sequence[ViewFiles], split: str) -> InputError:
  """The error for masks that are 0 everywhere (0 = ignore the pixel): training would fit no
  pixel and report a perfect, meaningless score."""
  folders = {view.mask.parent for view in chosen if view.mask is not None}
  where = folders.pop() if len(folders) == 1 else capture.root
  return InputError(f"every pixel of every mask of the {len(chosen)} {split} views is 0 "
                    "(0 = ignore the pixel), so no pixel is left to train or evaluate on; the "
                    "masks are likely inverted or empty", where, FILE_KEYS["mask"])


def load_views(root: str | os.PathLike, *, split: str = "train", downscale: int = 1,
               eval_every: int | None = None, held_out: Sequence[str] = (),
               scene_kind: str | None = None, scene_center=None,
               scene_radius: float | None = None) -> SceneViews:
  """The views `load_dataset` with these arguments reads, without reading their pixels: the
  cameras and the scene frame, in milliseconds (a dataset's images take seconds to decode)."""
  return _chosen_views(root, split, downscale, eval_every, held_out, scene_kind, scene_center,
                       scene_radius)[3]


def _chosen_views(root, split, downscale, eval_every, held_out, scene_kind, scene_center,
                  scene_radius) -> tuple[Capture, SceneFrame, np.ndarray, SceneViews]:
  """The capture, its scene frame, the indices of the split's views, and those views."""
  _check_options(downscale, scene_kind, scene_radius)
  capture = read_capture(root, downscale)
  frame = scene_frame(capture, scene_kind=scene_kind, scene_center=scene_center,
                      scene_radius=scene_radius)
  if (capture.format == "blender" and split == "eval" and eval_every is None and not held_out
      and not capture.source_splits.get("eval")):
    # Say which file holds no held-out view (the reader skips missing test images).
    raise blender.empty_test_split(capture.root)
  selected = splits.select_views(capture.names, split, source_splits=capture.source_splits,
                                 eval_every=eval_every, held_out=held_out, path=capture.root)
  cameras = poses_lib.transform_cameras(frame.world_from_source, capture.cameras)
  cameras = cameras.take(selected).downscaled(downscale)
  if min(cameras.width, cameras.height) < 1:
    full_size = f"{capture.cameras.width}x{capture.cameras.height}"
    raise InputError(f"{downscale} leaves no pixel of the {full_size} images (at most "
                     f"{min(capture.cameras.width, capture.cameras.height)})", capture.root,
                     "downscale")
  return capture, frame, selected, SceneViews(
      cameras=cameras, image_names=tuple(capture.names[index] for index in selected),
      scene_bounds=np.asarray(frame.bounds, np.float32), scene_kind=frame.kind,
      world_from_source=(frame.world_from_source
                         @ capture.file_from_source).astype(np.float32))


def _check_options(downscale, scene_kind, scene_radius) -> None:
  """Rejects a `downscale`, `scene_kind` or `scene_radius` `load_dataset` cannot take."""
  if isinstance(downscale, bool) or not isinstance(downscale, int) or downscale < 1:
    raise InputError(f"must be a positive integer, got {downscale!r}", field="downscale")
  if scene_kind is not None and scene_kind not in SCENE_KINDS:
    raise InputError(f"must be one of {SCENE_KINDS}, got {scene_kind!r}", field="scene_kind")
  if scene_radius is not None and not (isinstance(scene_radius, (int, float))
                                       and 0 < scene_radius < np.inf):
    raise InputError(f"must be a positive number, got {scene_radius!r}", field="scene_radius")


# Where each format's camera size comes from, for the error when a file has another size.
SIZE_SOURCES = {"llff": "poses_bounds.npy's hwf", "nerfstudio": "transforms.json's w and h",
                "colmap": "the COLMAP cameras", "blender": "the first image",
                "neus": "the first image"}


@dataclasses.dataclass(frozen=True)
class _ViewReader:
  """Reads the chosen views' files at the cameras' size, from prepared copies where they exist."""

  capture: Capture
  downscale: int
  target_size: tuple[int, int]

  def read_views(self, chosen: Sequence[ViewFiles], background: np.ndarray):
    """The chosen views' pixels at the cameras' size.

    Returns:
      images: [N, H, W, 3] float32 RGB in [0, 1], RGBA images composited on `background` ([3]).
      alphas: [N, H, W] float32 the images' opacity (1 for images without alpha).
      masks, depths, object_masks: [N, H, W] training masks in [0, 1], z-depths in the source's
        units and object ids; each None when no view has one (views without get 1, 0 and 0).
    """
    capture = self.capture
    color_and_alpha = self.read_all(
        chosen, "image", lambda p: views.read_color_and_alpha(p, background), "area", 0.0)
    images, alphas = color_and_alpha[..., :3], color_and_alpha[..., 3]
    masks = self.read_all(chosen, "mask", views.read_mask, "area", 1.0)
    depths = self.read_all(chosen, "depth",
                           lambda p: views.read_depth(p, capture.depth_unit_scale), "nearest",
                           0.0)
    read_object_ids = (views.read_silhouette if capture.silhouette_masks
                       else views.read_object_ids)
    object_masks = self.read_all(chosen, "object_mask", read_object_ids, "nearest", 0)
    return images, alphas, masks, depths, object_masks

  def read_all(self, chosen: Sequence[ViewFiles], kind: str, read, method: str, default):
    """[N, H, W(, C)] of each view's file of `kind`, or None when no view has one (views
    without get `default`)."""
    if all(getattr(view, kind) is None for view in chosen):
      return None
    arrays = []
    for view in chosen:
      path = getattr(view, kind)
      if path is None:
        arrays.append(np.full(self.target_size[::-1], default, np.float32))
        continue
      arrays.append(self._read(view, kind, path, read, method))
    return np.stack(arrays)

  def _read(self, view: ViewFiles, kind: str, path: Path, read, method: str) -> np.ndarray:
    capture = self.capture
    full_size = (capture.cameras.width, capture.cameras.height)
    prepared = None
    if capture.file_factor == 1 and self.downscale > 1:
      try:
        relative = path.relative_to(capture.root).as_posix()
      except ValueError:
        relative = None
      if relative is not None:
        prepared = views.prepared_downscale_path(capture.root, relative, self.downscale)
    if prepared is not None:
      file_size, tolerance = self.target_size, 1
    else:
      factor = capture.file_factor
      file_size = (round(full_size[0] / factor), round(full_size[1] / factor))
      tolerance = 0 if factor == 1 else 1
    return views.read_view(read, prepared or path, view.field(kind), file_size=file_size,
                           target_size=self.target_size, method=method,
                           size_tolerance=tolerance,
                           size_source=SIZE_SOURCES.get(capture.format, "the cameras"))
