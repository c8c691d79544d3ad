"""What the diffusion model is conditioned on in each camera: the NeRF render, the inpainting
mask and the control depth (paper, steps 4 and 6: "depth maps and inpainting masks from the
original NeRF scene").

For N cameras the NeRF is rendered (colour, median z-depth, opacity), the selection turns the
depth into a mask and a control depth (`geometry.selection`: box or proxy), the mask is dilated
and feathered (`geometry.masks`) and the control depth normalised to inverse depth over the
selection's own depth range in each camera (`geometry.control_depth`), so reference tiles and
dataset views show the selection in the same normalised band.

The training views need the render only where the selection, its mask and the control depth the
diffusion model sees can be (`pixels_to_render`): rendering just there costs the selection's
share of the pixels (`condition_views(..., only_where_selected_can_appear=True)`).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import numpy as np

from signerf_jax import camera as camera_lib
from signerf_jax.editing.config import SelectionConfig
from signerf_jax.editing.select import EditSelection
from signerf_jax.geometry import control_depth as control_depth_lib
from signerf_jax.geometry import image_rectangles
from signerf_jax.geometry import masks as masks_lib
from signerf_jax.geometry import mesh_depth
from signerf_jax.geometry import selection as selection_lib
from signerf_jax.nerf import model as nerf_model
from signerf_jax.nerf import render


@dataclasses.dataclass(frozen=True)
class Conditioning:
  """Per camera, [N, H, W] unless stated (rendered only near the selection: see `condition`).

  Attributes:
    render: [N, H, W, 3] the NeRF's colour render in [0, 1] (0 where not rendered).
    selected: bool, the selection as the cameras see it (before dilation).
    mask: float32 in [0, 1], the inpainting mask (dilated and feathered).
    control: float32 in [0, 1], normalised inverse control depth (near = 1; 0 where not
      rendered).
    control_depth: float32 control z-depth in scene units (+inf: nothing there, or not rendered).
  """

  render: np.ndarray
  selected: np.ndarray
  mask: np.ndarray
  control: np.ndarray
  control_depth: np.ndarray

  def arrays(self) -> dict[str, np.ndarray]:
    return dataclasses.asdict(self)

  def take(self, indices) -> "Conditioning":
    """The cameras at `indices` ([K] int)."""
    return Conditioning(**{name: array[indices] for name, array in self.arrays().items()})

  @classmethod
  def stack(cls, items) -> "Conditioning":
    """Single views (no leading axis) into one Conditioning."""
    return cls(**{field.name: np.stack([getattr(item, field.name) for item in items])
                  for field in dataclasses.fields(cls)})

  @classmethod
  def stack_chunks(cls, chunks) -> "Conditioning":
    """Conditionings of consecutive camera chunks into one."""
    return cls(**{field.name: np.concatenate([getattr(chunk, field.name) for chunk in chunks])
                  for field in dataclasses.fields(cls)})


# Pixels rendered beyond the mask's reach (already rounded up): a margin against an off-by-one
# in that reach, as the views stage trades a few pixels for certainty.
SAFETY_PIXELS = 2


def mask_reach(config: SelectionConfig, height: int, width: int) -> int:
  """Pixels from the selection's edge to the farthest nonzero pixel of its inpainting mask in an
  H x W image: the dilation radius plus the feather, scaled (`masks.scaled_radius`), rounded up
  (`masks.dilate_and_feather` keeps a pixel only when a selected pixel centre lies nearer)."""
  return math.ceil(masks_lib.scaled_radius(config.dilation_radius, height, width)
                   + masks_lib.scaled_radius(config.feather_radius, height, width))


def pixels_to_render(cameras: camera_lib.Cameras, edit_selection: EditSelection,
                     config: SelectionConfig, context_boxes=None) -> np.ndarray:
  """[N, H, W] bool: where the selection or its mask can appear in each camera, the rectangle of
  the pixels whose centre ray can meet the selection (`image_rectangles.points_rectangles` of
  its box corners or proxy vertices; the full frame for a camera with one of them behind it)
  grown by the mask's reach plus `SAFETY_PIXELS`, and the pixels inside `context_boxes`. A
  camera whose rectangle is empty (no pixel can show the selection) renders nothing.

  Args:
    context_boxes: None, or [N, 4] boxes [x0, y0, width, height] (pixels) whose control depth is
      wanted beyond the mask's reach (what the diffusion model sees around it), in the cameras
      that can show the selection.
  """
  growth = mask_reach(config, cameras.height, cameras.width) + SAFETY_PIXELS
  rectangles = image_rectangles.points_rectangles(cameras, edit_selection.points, growth)
  pixels = image_rectangles.rectangle_pixels(rectangles, cameras.height, cameras.width)
  if context_boxes is not None:
    # Only in views that can show the selection: the others are never inpainted.
    seen = rectangles[:, 2] > rectangles[:, 0]
    pixels |= image_rectangles.rectangle_pixels(
        image_rectangles.box_rectangles(context_boxes, cameras.height, cameras.width),
        cameras.height, cameras.width) & seen[:, None, None]
  return pixels


def _derive(cameras: camera_lib.Cameras, renders: dict[str, np.ndarray],
            edit_selection: EditSelection, config: SelectionConfig) -> Conditioning:
  """The selection, masks and control depth of N cameras from their NeRF `renders`
  (`render.render_cameras`' outputs, [N, H, W, ...]); see the module docstring."""
  # The median depth: a pixel straddling a silhouette takes one surface's depth, not a blend.
  depth, accumulation = renders["median_depth"], renders["accumulation"]
  if edit_selection.kind == "box":
    selected = selection_lib.shape_selection(
        cameras, edit_selection.box, depth, accumulation, mask_mode=config.box_mask_mode,
        min_accumulation=config.min_accumulation)
  else:
    proxy_depth = mesh_depth.render_mesh_depth(edit_selection.proxy, cameras).z_depth
    selected = selection_lib.proxy_selection(cameras, depth, proxy_depth, accumulation,
                                             min_accumulation=config.min_accumulation)
  mask = masks_lib.dilate_and_feather(selected.mask, radius=config.dilation_radius,
                                      feather=config.feather_radius)
  center, radius = edit_selection.sphere()
  near, far = control_depth_lib.selection_depth_range(cameras, center, radius)
  control = control_depth_lib.normalize_control_depth(selected.control_depth, near, far)
  as_numpy = lambda array: np.asarray(jax.device_get(array), np.float32)
  return Conditioning(render=as_numpy(renders["rgb"]), selected=np.asarray(selected.mask, bool),
                      mask=as_numpy(mask), control=as_numpy(control),
                      control_depth=as_numpy(selected.control_depth))


def condition(model: nerf_model.NerfModel, variables, cameras: camera_lib.Cameras,
              edit_selection: EditSelection, config: SelectionConfig, *,
              only_where_selected_can_appear: bool = False, context_boxes=None) -> Conditioning:
  """Renders `cameras` with the NeRF and derives masks and control depth (module docstring).

  Args:
    only_where_selected_can_appear: False renders full frames (figures and metrics need every
      pixel). True renders only `pixels_to_render` (with `context_boxes`): selected and mask are
      then those of full frames everywhere (no selection can lie outside), render, control and
      control_depth those of full frames there; elsewhere render and control are 0 and
      control_depth +inf (nothing there).
    context_boxes: see `pixels_to_render` (only with `only_where_selected_can_appear`).
  """
  pixels = (pixels_to_render(cameras, edit_selection, config, context_boxes)
            if only_where_selected_can_appear else None)
  renders = render.render_cameras(model, variables, cameras, pixels=pixels)
  return _derive(cameras, renders, edit_selection, config)


def condition_views(model: nerf_model.NerfModel, variables, cameras: camera_lib.Cameras,
                    indices, edit_selection: EditSelection, config: SelectionConfig,
                    chunk_size: int, *, only_where_selected_can_appear: bool = False,
                    context_boxes=None) -> Conditioning:
  """`condition` of the cameras at `indices` (at most `chunk_size`). Their renders are derived
  for exactly `chunk_size` cameras (the last one repeated, not rendered again) so that every
  chunk reuses one compilation.

  Args:
    only_where_selected_can_appear: see `condition`.
    context_boxes: None or [N, 4] boxes of all N `cameras` (`pixels_to_render`).
  """
  indices = np.asarray(indices, np.int64)
  chosen = cameras.take(indices)
  padding = np.repeat(len(indices) - 1, chunk_size - len(indices))
  padded = np.concatenate([np.arange(len(indices)), padding])
  padded_cameras = chosen.take(padded)
  pixels = None
  if only_where_selected_can_appear:
    # Found for the padded cameras too: a last, shorter chunk compiles no program of its own.
    pixels = pixels_to_render(padded_cameras, edit_selection, config,
                              None if context_boxes is None else
                              np.asarray(context_boxes)[indices][padded])[:len(indices)]
  renders = render.render_cameras(model, variables, chosen, pixels=pixels)
  conditioned = _derive(padded_cameras, {name: array[padded] for name, array
                                              in renders.items()}, edit_selection, config)
  return conditioned.take(np.arange(len(indices)))


def condition_in_chunks(model: nerf_model.NerfModel, variables, cameras: camera_lib.Cameras,
                        edit_selection: EditSelection, config: SelectionConfig,
                        chunk_size: int) -> Conditioning:
  """`condition` of every camera (full frames), `chunk_size` at a time (`condition_views`): its
  programs are compiled for `chunk_size` cameras whatever their number, so the reference tiles,
  the training views and the held-out views of an edit share them where their sizes agree."""
  count = cameras.num_cameras
  return Conditioning.stack_chunks([
      condition_views(model, variables, cameras, chunk, edit_selection, config, chunk_size)
      for chunk in np.array_split(np.arange(count), -(-count // chunk_size))])
