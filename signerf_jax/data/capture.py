"""What a reader finds in a dataset directory, before anything is normalised.

Every reader (nerfstudio, Blender, LLFF, COLMAP, NeuS/IDR) turns its files into one `Capture`:
the cameras in the source's own world frame and units (OpenGL camera-to-world, full
resolution), where each view's files are, which views the source itself holds out, and what it
knows about the scene (SfM points, per-view depth ranges, an object sphere, a finished frame).
`load.load_dataset` then picks the split, estimates the scene frame (`frame.estimate_frame`)
and reads only the chosen views' pixels.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from signerf_jax.camera import Cameras
from signerf_jax.data.frame import SceneFrame


@dataclasses.dataclass(frozen=True)
class ViewFiles:
  """One view's files.

  Attributes:
    image: the colour image (8/16-bit PNG or JPEG; RGBA is composited on the background).
    mask: None or a validity mask (nerfstudio `mask_path`: 0 = ignore the pixel in training).
    depth: None or a z-depth map (EXR as stored, 16-bit PNG times the capture's depth scale).
    object_mask: None or an 8-bit object-id map (0 = no object; NeuS/IDR masks become id 1).
    label: where the source names this view, for errors (e.g. "frames[3]"); a file's field is
      the label and nerfstudio's key for it (e.g. "frames[3].mask_path").
  """

  image: Path
  mask: Path | None = None
  depth: Path | None = None
  object_mask: Path | None = None
  label: str = ""

  def field(self, kind: str) -> str:
    """The field naming this view's file of `kind` ("image", "mask", "depth", "object_mask")."""
    key = FILE_KEYS[kind]
    return f"{self.label}.{key}" if self.label else key


# nerfstudio's per-frame key for each kind of view file: the names errors use for every format.
FILE_KEYS = {"image": "file_path", "mask": "mask_path", "depth": "depth_file_path",
             "object_mask": "object_mask_path"}


@dataclasses.dataclass(frozen=True)
class Capture:
  """A dataset as its files describe it, in the source's world frame and units.

  Attributes:
    root: the dataset directory.
    cameras: all N views, full resolution, OpenGL camera-to-world in the source frame.
    names: N image names as the source lists them (paths relative to `root`), unique.
    files: N ViewFiles.
    source_splits: the views the source assigns to "train" and "eval" (index tuples), or None
      when it has no split of its own (then every `eval_every`-th view is held out).
    points: None or [P, 3] float64 sparse SfM points in the source frame.
    depth_bounds: None or [N, 2] float64 near/far z-depths of each view's content (LLFF).
    object_sphere: None or (centre [3], radius): a sphere the source says holds the object of
      interest (NeuS/IDR `scale_mat`).
    frame: None, or the frame the source fixes completely (a signerf-written dataset, a Blender
      scene); then nothing is estimated.
    kind: None (infer), or the scene kind the source implies ("bounded" for transparent
      backgrounds).
    background_color: None, or the [3] colour the source says its scene was made with (RGBA
      images are composited on it; bounded scenes see it through empty space).
    depth_unit_scale: 16-bit PNG depth units in source units (nerfstudio's
      `depth_unit_scale_factor`).
    file_from_source: [4, 4] similarity from the capture's original frame into the frame the
      cameras are given in (nerfstudio's `applied_transform`; identity for other formats).
    file_factor: the view files are stored downscaled by this factor relative to the cameras'
      resolution (LLFF's `images_N/`); 1 = full size, and `images_N/`-style prepared copies are
      looked up when reading at a downscale.
    silhouette_masks: the object masks are black-and-white silhouettes (NeuS/IDR, grey or RGB:
      a first channel above 0.5 is the object, id 1) rather than 8-bit object-id maps.
    format: the reader's name, for messages.
  """

  root: Path
  cameras: Cameras
  names: tuple[str, ...]
  files: tuple[ViewFiles, ...]
  source_splits: dict[str, tuple[int, ...]] | None = None
  points: np.ndarray | None = None
  depth_bounds: np.ndarray | None = None
  object_sphere: tuple[np.ndarray, float] | None = None
  frame: SceneFrame | None = None
  kind: str | None = None
  background_color: np.ndarray | None = None
  depth_unit_scale: float = 1e-3
  file_from_source: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
  file_factor: int = 1
  silhouette_masks: bool = False
  format: str = ""

  def __post_init__(self):
    count = self.cameras.num_cameras
    if len(self.names) != count or len(self.files) != count:
      raise ValueError(f"{count} cameras, {len(self.names)} names and {len(self.files)} view "
                       "files do not match")
    if len(set(self.names)) != count:
      raise ValueError("image names must be unique")
