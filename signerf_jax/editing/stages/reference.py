"""The reference stage (paper, Sec. 3 steps 3-4): place the reference cameras around the selection
and render their tiles (colour, mask, control depth). In a second iteration the cameras, masks
and control stay those of the first; the colour comes from the edited NeRF."""

from __future__ import annotations

from typing import Any

import numpy as np

from signerf_jax import camera as camera_lib
from signerf_jax import files
from signerf_jax.data import poses
from signerf_jax.editing import conditioning as conditioning_lib
from signerf_jax.editing import figures
from signerf_jax.editing.config import as_json
from signerf_jax.editing.project import load_arrays, save_arrays
from signerf_jax.editing.stages.context import EditContext
from signerf_jax.editing.stages.inputs import VIEWS_PER_CHUNK
from signerf_jax.errors import InputError
from signerf_jax.geometry import reference_cameras

# Kept from the first iteration's tiles in later iterations.
GEOMETRY_ARRAYS = ("selected", "mask", "control", "control_depth")


def reference_settings(context: EditContext) -> dict[str, Any]:
  """The reference stage's key: the sheet layout, the model and the camera placement."""
  return {"sheet": as_json(context.settings.sheet), "model": context.settings.edit.model,
          "placement": as_json(context.settings.placement)}


def read_reference_cameras(path: str, count: int, tile_size: int) -> camera_lib.Cameras:
  """User-given reference cameras: a Blender-style JSON (camera_angle_x, frames)."""
  meta = files.read_json(path)
  frames = meta.get("frames")
  if not isinstance(frames, list) or len(frames) != count:
    raise InputError(f"needs exactly {count} frames (one per sheet tile)", path, "frames")
  angle = meta.get("camera_angle_x")
  if isinstance(angle, bool) or not isinstance(angle, (int, float)) or not 0 < angle < np.pi:
    raise InputError(f"must be a field of view in (0, pi) radians, got {angle!r}", path,
                     "camera_angle_x")
  camera_to_world = np.stack([poses.check_camera_to_world(frame.get("transform_matrix"), path,
                                                          f"frames[{index}].transform_matrix")
                              for index, frame in enumerate(frames)])
  focal = 0.5 * tile_size / np.tan(angle / 2)
  return camera_lib.Cameras.create(camera_to_world, focal, width=tile_size, height=tile_size)


def cameras_to_json(cameras: camera_lib.Cameras) -> dict[str, Any]:
  """`cameras` as JSON-ready fields (arrays stay numpy: `files.write_json` converts them)."""
  return {"camera_to_world": np.asarray(cameras.camera_to_world), "fx": np.asarray(cameras.fx),
          "fy": np.asarray(cameras.fy), "width": cameras.width, "height": cameras.height}


def cameras_from_json(value: dict[str, Any]) -> camera_lib.Cameras:
  """The cameras `cameras_to_json` wrote (read back from the reference's cameras.json)."""
  return camera_lib.Cameras.create(np.asarray(value["camera_to_world"]), np.asarray(value["fx"]),
                                   np.asarray(value["fy"]), width=value["width"],
                                   height=value["height"])


def first_iteration_cameras(context: EditContext, points=None):
  """(cameras, report): the user's reference cameras, or placed around the selection (its
  `points` [K, 3], scene frame; default the context's selection)."""
  config = context.settings.sheet
  points = context.selection.points if points is None else points
  count, size = context.layout.num_tiles, context.tile_size
  if config.reference_cameras:
    cameras = read_reference_cameras(config.reference_cameras, count, size)
    return cameras, reference_cameras.describe_reference_cameras(
        cameras, context.views.cameras, points, context.settings.placement.up)
  return reference_cameras.place_reference_cameras(
      context.views.cameras, points, count=count, placement=context.settings.placement,
      width=size, height=size)


def render_reference(context: EditContext, iteration: int = 1) -> str:
  """Steps 3-4: places the reference cameras (or reads the user's; a later iteration reuses the
  first's) and renders their tiles from the NeRF before this iteration.

  Writes reference/inputs.npz (render, mask, control, ... [N, S, S, ...] per tile), cameras.json
  and tiles.png; returns the summary line."""
  layout = context.layout
  directory = context.directory.path("reference", iteration=iteration)
  if iteration == 1:
    cameras, report = first_iteration_cameras(context)
    nerf = context.nerf(0)
  else:
    cameras = cameras_from_json(files.read_json(context.directory.path("reference",
                                                                       "cameras.json")))
    report, nerf = None, context.nerf(iteration - 1)
  # In the training views' chunks: where tiles and views have one size, they share programs.
  arrays = conditioning_lib.condition_in_chunks(nerf.model, nerf.variables, cameras,
                                                context.selection, context.settings.selection,
                                                VIEWS_PER_CHUNK).arrays()
  if iteration > 1:
    first = load_arrays(context.directory.path("reference", "inputs.npz"), GEOMETRY_ARRAYS)
    arrays.update({name: first[name] for name in GEOMETRY_ARRAYS})
  save_arrays(directory / "inputs.npz", **arrays)
  files.write_json(directory / "cameras.json", {
      **cameras_to_json(cameras), "report": None if report is None else report.to_json()})
  tiles_png = directory / "tiles.png"
  count = layout.num_tiles
  files.write_image(tiles_png, figures.image_grid(
      [list(arrays["render"]), list(arrays["mask"]), list(arrays["control"])],
      [[f"tile {index}" for index in range(count)], ["mask"] * count, ["control"] * count]))
  fill = "" if report is None else (
      f", selection fills {np.min(report.fill_ratio):.0%}-{np.max(report.fill_ratio):.0%} of "
      "the frames")
  source = "edited" if iteration > 1 else "original"
  # The growth is the model's unless bound (`commands.edit_settings`): say which one is in use.
  growth = context.settings.selection.dilation_radius
  return (f"{count} reference views of {context.tile_size} px rendered from the {source} "
          f"NeRF{fill}, masks grown {growth:g} px at 512: {tiles_png}")
