"""The views of one sample: its cameras, and rendering them.

A sample is rendered by the synthetic ray caster either
  * as a single view (1 camera), or
  * as a multi-view sheet: `sheet_tiles` reference views then one slot view (6 for the 2 x 3
    sheet), all of the same object with one appearance under one light, in the order
    `signerf_jax.editing.sheet` takes them (tiles in grid order skipping the slot, then the slot).
Cameras come as in the editing pipeline. A "dataset" rig like the synthetic scenes' (hemisphere
or forward-facing, random distance, field of view, elevations and a random turn about the
vertical) looks at the scene centre; "reference" cameras are placed around the object from that
rig by `signerf_jax.geometry.reference_cameras.place_reference_cameras` (the object roughly
centred; its bounding sphere fills a random fraction of the frame within `fill_range`). A "crop"
view is a dataset camera that sees the object, cut down to the crop around the object that the
pipeline's selection crops take of a dataset view (`editing.crops.selection_crop_boxes`, with a
random margin in `crop_margin_range`; the object may sit off-centre where the crop meets the
frame's edge) and rendered directly at the tile size: what the shipped model is given in the
image set update with `SheetConfig.crops`. (Whole 64-pixel dataset frames, where an object
covers a few percent of the pixels, are left out: at this size neither the VAE nor the
diffusion model can draw such an object.) The sheet's tiles are reference views; its slot view
is a crop view with probability `slot_crop_view_probability`, else one more reference view. A
single view is a reference view with probability `reference_view_probability`, else a crop
view.
"""

from __future__ import annotations

import jax
import numpy as np
import trimesh

from signerf_jax import camera as camera_lib
from signerf_jax.data import poses as poses_lib
from signerf_jax.data import synthetic, synthetic_render
from signerf_jax.default_model import scenes
from signerf_jax.editing import crops
from signerf_jax.geometry import control_depth
from signerf_jax.geometry import masks
from signerf_jax.geometry import reference_cameras


def dataset_rig(rng: np.random.Generator, settings: scenes.SceneSampling, scene_bounds
                ) -> camera_lib.Cameras:
  """A random rig like the synthetic scenes' cameras, turned by a random angle about the
  vertical."""
  rig = synthetic_render.CameraRig(
      layout="forward_facing" if rng.uniform() < settings.rig_forward_facing_probability
      else "hemisphere",
      num_views=settings.rig_views, image_size=settings.image_size,
      field_of_view_degrees=rng.uniform(*settings.rig_field_of_view_degrees_range),
      distance=rng.uniform(*settings.rig_distance_range),
      elevation_range_degrees=(rng.uniform(*settings.rig_low_elevation_degrees_range),
                               rng.uniform(*settings.rig_high_elevation_degrees_range)),
      arc_degrees=rng.uniform(*settings.rig_arc_degrees_range))
  cameras = synthetic_render.make_cameras(rig, scene_bounds)
  target = np.mean(np.asarray(scene_bounds, np.float64), axis=0)
  turn = trimesh.transformations.rotation_matrix(rng.uniform(0, 2 * np.pi), (0.0, 0.0, 1.0),
                                                 point=target)
  return poses_lib.transform_cameras(turn, cameras)


def sample_cameras(rng, settings: scenes.SceneSampling, scene, num_views: int, sheet: bool):
  """(cameras, view kinds: indices into `samples.VIEW_KINDS`) for a single view (num_views 1) or
  a sheet (module docstring), or None if no camera of the dataset rig sees the object."""
  dataset_cameras = dataset_rig(rng, settings, scene.scene_bounds)
  corners = scenes.object_corners(scene)
  seeing = np.flatnonzero(reference_cameras.cameras_seeing(dataset_cameras, corners))
  if not len(seeing):
    return None
  # The generator's own placement, not the edit's gin-bound `ReferencePlacement`: the dataset
  # must not change with an edit's settings.
  placement = reference_cameras.ReferencePlacement(
      up=(0.0, 0.0, 1.0), min_fill=rng.uniform(*settings.fill_range),
      max_fill=settings.fill_range[1])
  references, _ = reference_cameras.place_reference_cameras(
      dataset_cameras, corners, count=settings.sheet_tiles + 1, placement=placement)
  dataset_view = dataset_cameras.take([seeing[rng.integers(len(seeing))]])
  # Drawn for every sample, used or not, so that the random stream (the dataset) stays the same.
  crop_margin = rng.uniform(*settings.crop_margin_range)

  def crop_view():
    size = settings.image_size
    box = crops.selection_crop_boxes(dataset_view, corners, size, size, crop_margin,
                                     settings.crop_max_upscale)
    return jax.tree.map(np.asarray, dataset_view.cropped(box, size, size))

  if sheet:
    if rng.uniform() < settings.slot_crop_view_probability:
      tiles = references.take(slice(0, num_views - 1))
      return (jax.tree.map(lambda *arrays: np.concatenate(arrays), tiles, crop_view()),
              [0] * (num_views - 1) + [1])
    return references, [0] * num_views
  if rng.uniform() < settings.reference_view_probability:
    return references.take([rng.integers(references.num_cameras)]), [0]
  return crop_view(), [1]


def bounding_boxes(silhouette: np.ndarray) -> np.ndarray:
  """[V, 4] int16 [x0, y0, x1, y1) pixel bounds of each nonempty [V, H, W] silhouette."""
  rows, columns = silhouette.any(2), silhouette.any(1)
  first = lambda occupied: np.argmax(occupied, -1)
  last = lambda occupied: occupied.shape[-1] - np.argmax(occupied[:, ::-1], -1)
  return np.stack([first(columns), first(rows), last(columns), last(rows)], -1).astype(np.int16)


def render_views(scene: synthetic.SyntheticScene, background_scene: synthetic.SyntheticScene,
                 cameras: camera_lib.Cameras, settings: scenes.SceneSampling
                 ) -> dict[str, np.ndarray]:
  """The per-view arrays of the `samples` module docstring (without view_kinds)."""
  rgb, depth, object_ids = synthetic_render.render(scene, cameras)
  background_rgb, _, _ = synthetic_render.render(background_scene, cameras)
  silhouette = object_ids == scenes.OBJECT_ID
  dilated = np.stack([np.asarray(masks.dilate_and_feather(
      silhouette, radius=float(radius), reference_size=settings.image_size))
                      for radius in settings.dilation_radii], 1)
  center, radius = reference_cameras.selection_sphere(scenes.object_corners(scene))
  near, far = control_depth.selection_depth_range(cameras, center, radius)
  to_uint8 = lambda image: np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)
  return {
      "rgb": to_uint8(rgb), "background_rgb": to_uint8(background_rgb),
      "depth": depth.astype(np.float16), "silhouette": silhouette.astype(np.uint8),
      "dilated_silhouettes": dilated.astype(np.uint8), "boxes": bounding_boxes(silhouette),
      "control_near_far": np.stack([near, far], -1).astype(np.float32),
      "camera_to_world": np.asarray(cameras.camera_to_world, np.float32),
      "intrinsics": np.stack([cameras.fx, cameras.fy, cameras.cx, cameras.cy], -1).astype(
          np.float32),
  }
