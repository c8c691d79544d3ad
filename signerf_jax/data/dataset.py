"""The in-memory dataset every reader produces and every consumer (NeRF, editing) reads."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from signerf_jax.camera import Cameras
from signerf_jax.data.frame import SCENE_KINDS


@dataclasses.dataclass(frozen=True)
class SceneViews:
  """A dataset's views without their pixels: what placing a selection and cameras in the scene
  needs (`load.load_views` reads it without decoding an image). Attributes as `Dataset`'s."""

  cameras: Cameras
  image_names: tuple[str, ...]
  scene_bounds: np.ndarray
  scene_kind: str
  world_from_source: np.ndarray

  @property
  def num_images(self) -> int:
    return len(self.image_names)


@dataclasses.dataclass(frozen=True)
class Dataset:
  """Images with their cameras, in the normalised scene frame.

  Attributes:
    images: [N, H, W, 3] float32 RGB in [0, 1] (RGBA already composited on `background_color`).
    cameras: N cameras (OpenGL camera-to-world, normalised scene frame).
    image_names: N paths of the images relative to the dataset root, as the source lists them.
    scene_bounds: [2, 3] float32 (min corner, max corner) of the region the NeRF must model.
    scene_kind: "bounded" (object inside the bounds, constant background), "forward_facing"
      (LLFF-style) or "unbounded" (360 degree with distant background: needs contraction).
    near, far: float ray range in scene units covering the content for every camera.
    background_color: [3] float32 RGB for bounded scenes (None when the background is real).
    world_from_source: [4, 4] float32 similarity transform from the source's world frame into
      the normalised frame (points: x_normalised = world_from_source @ x_source).
    alphas: None or [N, H, W] float32 opacity of images that had an alpha channel (`images`
      holds them composited on `background_color`); lets training see through to other
      backgrounds.
    masks: None or [N, H, W] float32 in [0, 1]; 1 = pixel is valid for training (nerfstudio
      `mask_path` semantics).
    depths: None or [N, H, W] float32 z-depth in normalised scene units; 0 = unknown.
    extras: per-view ground truth a source may carry, e.g. {"object_masks": [N, H, W] int32}.
    root: the directory the dataset was read from ("" for in-memory datasets).
    frame: None, or how the scene frame was found (`SceneFrame.describe`: kind, the inner
      region's centre and size in the source's units, near/far).
  """

  images: np.ndarray
  cameras: Cameras
  image_names: tuple[str, ...]
  scene_bounds: np.ndarray
  scene_kind: str
  near: float
  far: float
  background_color: np.ndarray | None = None
  world_from_source: np.ndarray = dataclasses.field(
      default_factory=lambda: np.eye(4, dtype=np.float32))
  alphas: np.ndarray | None = None
  masks: np.ndarray | None = None
  depths: np.ndarray | None = None
  extras: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
  root: str = ""
  frame: dict[str, Any] | None = None

  def __post_init__(self):
    if self.scene_kind not in SCENE_KINDS:
      raise ValueError(f"scene_kind must be one of {SCENE_KINDS}, got {self.scene_kind!r}")
    count = len(self.image_names)
    if self.images.shape[0] != count or self.cameras.num_cameras != count:
      raise ValueError(f"{self.images.shape[0]} images, {self.cameras.num_cameras} cameras and "
                       f"{count} names do not match")

  @property
  def num_images(self) -> int:
    return len(self.image_names)

  @property
  def views(self) -> SceneViews:
    """The views without their pixels."""
    return SceneViews(self.cameras, self.image_names, self.scene_bounds, self.scene_kind,
                      self.world_from_source)

  @property
  def height(self) -> int:
    return self.images.shape[1]

  @property
  def width(self) -> int:
    return self.images.shape[2]

  def subset(self, indices) -> "Dataset":
    """The views at `indices` (any integer sequence), all per-view arrays sliced alike."""
    indices = np.asarray(indices, np.int64).reshape(-1)
    take = lambda array: None if array is None else array[indices]
    return dataclasses.replace(
        self,
        images=self.images[indices],
        cameras=self.cameras.take(indices),
        image_names=tuple(self.image_names[i] for i in indices),
        alphas=take(self.alphas),
        masks=take(self.masks),
        depths=take(self.depths),
        extras={name: array[indices] for name, array in self.extras.items()},
    )

  def summary(self) -> dict[str, Any]:
    """A JSON-friendly description (sizes, bounds, kind), for logs and run directories."""
    return {
        "root": self.root,
        "num_images": self.num_images,
        "height": self.height,
        "width": self.width,
        "scene_kind": self.scene_kind,
        "scene_bounds": np.asarray(self.scene_bounds).tolist(),
        "near": float(self.near),
        "far": float(self.far),
        "has_depths": self.depths is not None,
        "has_masks": self.masks is not None,
        "frame": self.frame,
    }
