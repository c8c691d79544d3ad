"""Step 2, object selection: the box or placed proxy mesh of an edit, in the NeRF's scene frame.

`build_selection` turns a `SelectionConfig` into an `EditSelection` and checks it against the
dataset: the box is well formed, the proxy file exists and holds triangles, some dataset camera
sees the selection, and (bounded scenes) it lies inside the region the NeRF models. Each failure
is an InputError naming the setting at fault.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np

from signerf_jax import files
from signerf_jax.data import poses as poses_lib
from signerf_jax.data.dataset import SceneViews
from signerf_jax.editing.config import PRIMITIVE_PREFIX, SelectionConfig
from signerf_jax.errors import InputError
from signerf_jax.geometry import mesh as mesh_lib
from signerf_jax.geometry import primitives
from signerf_jax.geometry import reference_cameras
from signerf_jax.geometry import selection as selection_lib

PRIMITIVES = {"box": primitives.box, "sphere": primitives.sphere,
              "cylinder": primitives.cylinder, "capsule": primitives.capsule,
              "cow": primitives.primitive_cow}
# A selection may poke this far (scene units) out of a bounded scene's box before it is an error.
BOUNDS_TOLERANCE = 0.02


@dataclasses.dataclass(frozen=True)
class EditSelection:
  """A selection in the scene frame.

  Attributes:
    kind: "box" or "proxy".
    box: the box (kind "box").
    proxy: the placed proxy mesh (kind "proxy").
  """

  kind: str
  box: selection_lib.Box | None = None
  proxy: mesh_lib.Mesh | None = None

  @property
  def points(self) -> np.ndarray:
    """[K, 3] points spanning the selection: the box corners or the proxy's vertices."""
    if self.kind == "box":
      return np.asarray(self.box.corners, np.float64)
    return np.asarray(self.proxy.vertices, np.float64)

  @property
  def bounds(self) -> np.ndarray:
    """[2, 3] axis-aligned bounds."""
    points = self.points
    return np.stack([points.min(0), points.max(0)])

  def grown_bounds(self, margin: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """((min x, y, z), (max x, y, z)): `bounds` grown on every side by `margin` times the
    largest side (the edited NeRF's region, `FinetuneConfig.edit_region`)."""
    lower, upper = self.bounds
    grow = margin * float(np.max(upper - lower))
    return tuple(map(float, lower - grow)), tuple(map(float, upper + grow))

  def sphere(self) -> tuple[np.ndarray, float]:
    """Centre and radius of a sphere around the selection (control depth range, cameras)."""
    return reference_cameras.selection_sphere(self.points)

  def describe(self) -> dict[str, Any]:
    center, radius = self.sphere()
    description = {"kind": self.kind, "bounds": self.bounds, "center": center, "radius": radius}
    if self.kind == "proxy":
      description.update(source=self.proxy.source, vertices=len(self.proxy.vertices),
                         triangles=len(self.proxy.faces))
    return description


def load_proxy(name: str) -> mesh_lib.Mesh:
  """A proxy mesh file, or a primitive given as "primitive:<name>" (in its own frame)."""
  if name.startswith(PRIMITIVE_PREFIX):
    primitive = name[len(PRIMITIVE_PREFIX):]
    if primitive not in PRIMITIVES:
      raise InputError(f"unknown primitive {primitive!r} (known: {', '.join(PRIMITIVES)})",
                       field="proxy")
    return PRIMITIVES[primitive]()
  if not Path(name).is_file():
    raise InputError("proxy mesh file not found", name, "proxy")
  try:
    return mesh_lib.load_mesh(name)
  except InputError as error:
    raise InputError(error.problem, error.path, "proxy") from None


def up_direction(config: SelectionConfig, views: SceneViews) -> np.ndarray:
  """The up direction in the configured frame: `config.up`, or the cameras' mean up."""
  if config.up is not None:
    return np.asarray(config.up, np.float64)
  up = reference_cameras.scene_up(views.cameras)  # The dataset's cameras are in the scene frame.
  if config.frame == "source":
    up = np.linalg.inv(views.world_from_source[:3, :3]) @ up
  return up


def place_proxy(config: SelectionConfig, views: SceneViews) -> mesh_lib.Mesh:
  """The proxy of `config`, placed (in the configured frame, then mapped into the scene's)."""
  proxy = load_proxy(config.proxy)
  if config.ground_position is not None:
    if not config.ground_size > 0:
      raise InputError(f"must be positive, got {config.ground_size}", field="ground_size")
    placed = mesh_lib.place_on_ground(proxy, config.ground_position, config.ground_size,
                                      up=up_direction(config, views),
                                      mesh_up=config.mesh_up,
                                      heading_degrees=config.heading_degrees)
  else:
    placed = mesh_lib.transform_mesh(proxy, mesh_lib.similarity_transform(
        config.scale, config.rotation_degrees, config.translation))
  if config.frame == "source":
    placed = mesh_lib.transform_mesh(placed, views.world_from_source)
  return placed


def make_box(config: SelectionConfig, views: SceneViews) -> selection_lib.Box:
  """The configured box in the scene frame (a source-frame box becomes the scene-frame box
  around its rotated corners)."""
  try:
    lower, upper = (np.asarray(corner, np.float64) for corner in (config.box_min, config.box_max))
  except (TypeError, ValueError):
    raise InputError("box corners must be numbers", field="box") from None
  if lower.shape != (3,) or upper.shape != (3,):
    raise InputError("box corners must be 3-vectors (min x y z, max x y z)", field="box")
  box = selection_lib.Box.create(lower, upper)
  if config.frame == "source":
    corners = poses_lib.transform_points(views.world_from_source, np.asarray(box.corners))
    box = selection_lib.Box.create(corners.min(0), corners.max(0))
  return box


def build_selection(config: SelectionConfig, views: SceneViews) -> EditSelection:
  """The selection of `config`, checked against `views` (see the module docstring)."""
  if config.kind == "box":
    edit_selection = EditSelection("box", box=make_box(config, views))
  else:
    edit_selection = EditSelection("proxy", proxy=place_proxy(config, views))
  lower, upper = edit_selection.bounds
  if views.scene_kind == "bounded":
    scene_lower, scene_upper = np.asarray(views.scene_bounds, np.float64)
    if np.any(lower < scene_lower - BOUNDS_TOLERANCE) or np.any(upper > scene_upper +
                                                                 BOUNDS_TOLERANCE):
      raise InputError(f"the selection spans {lower.round(3).tolist()} .. "
                       f"{upper.round(3).tolist()}, outside the scene bounds "
                       f"{scene_lower.round(3).tolist()} .. {scene_upper.round(3).tolist()} the "
                       "NeRF models", field="selection")
  if not reference_cameras.cameras_seeing(views.cameras, edit_selection.points).any():
    raise InputError(f"none of the {views.num_images} dataset cameras sees the selection "
                     f"({lower.round(3).tolist()} .. {upper.round(3).tolist()})",
                     field="selection")
  return edit_selection


def write_selection(directory: str | os.PathLike, edit_selection: EditSelection) -> list[Path]:
  """selection.json (and proxy.ply, the placed proxy) in `directory`; returns the paths."""
  directory = Path(directory)
  written = [directory / "selection.json"]
  description = edit_selection.describe()
  if edit_selection.kind == "box":
    description.update(box_min=np.asarray(edit_selection.box.minimum),
                       box_max=np.asarray(edit_selection.box.maximum))
  else:
    written.append(directory / "proxy.ply")
    with files.atomic_path(written[1]) as temporary:
      edit_selection.proxy.to_trimesh().export(temporary)
  files.write_json(written[0], description)
  return written
