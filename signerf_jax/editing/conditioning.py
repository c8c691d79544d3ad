"""What the diffusion model is conditioned on in each camera: the NeRF render, the inpainting
mask and the control depth (paper, steps 4 and 6: "depth maps and inpainting masks from the
original NeRF scene").

For N cameras the NeRF is rendered (colour, median z-depth, opacity), the selection turns the
depth into a mask and a control depth (`geometry.selection`: box or proxy), the mask is dilated
and feathered (`geometry.masks`) and the control depth normalised to inverse depth over the
selection's own depth range in each camera (`geometry.control_depth`), so reference tiles and
dataset views show the selection in the same normalised band.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from signerf_jax import camera as camera_lib
from signerf_jax.editing.config import SelectionConfig
from signerf_jax.editing.select import EditSelection
from signerf_jax.geometry import control_depth as control_depth_lib
from signerf_jax.geometry import masks as masks_lib
from signerf_jax.geometry import mesh_depth
from signerf_jax.geometry import selection as selection_lib
from signerf_jax.nerf import model as nerf_model
from signerf_jax.nerf import render


@dataclasses.dataclass(frozen=True)
class Conditioning:
  """Per camera, [N, H, W] unless stated.

  Attributes:
    render: [N, H, W, 3] the NeRF's colour render in [0, 1].
    selected: bool, the selection as the cameras see it (before dilation).
    mask: float32 in [0, 1], the inpainting mask (dilated and feathered).
    control: float32 in [0, 1], normalised inverse control depth (near = 1).
    control_depth: float32 control z-depth in scene units (+inf: nothing there).
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


def condition(model: nerf_model.NerfModel, variables, cameras: camera_lib.Cameras,
              edit_selection: EditSelection, config: SelectionConfig) -> Conditioning:
  """Renders `cameras` with the NeRF and derives masks and control depth (module docstring)."""
  renders = render.render_cameras(model, variables, cameras)
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


def condition_views(model: nerf_model.NerfModel, variables, cameras: camera_lib.Cameras,
                    indices, edit_selection: EditSelection, config: SelectionConfig,
                    chunk_size: int) -> Conditioning:
  """`condition` of the cameras at `indices` (at most `chunk_size`), computed for exactly
  `chunk_size` cameras (the last one repeated) so that every chunk reuses one compilation."""
  indices = np.asarray(indices, np.int64)
  padded = np.concatenate([indices, np.repeat(indices[-1:], chunk_size - len(indices))])
  conditioned = condition(model, variables, cameras.take(padded), edit_selection, config)
  return Conditioning(**{name: array[:len(indices)]
                         for name, array in conditioned.arrays().items()})
