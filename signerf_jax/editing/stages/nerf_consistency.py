"""Part of the evaluate stage: is the edited object solid and consistent in the NeRF itself?

The paper's claim is that sheet-propagated images agree across views, so the NeRF fitted to them
converges to a crisp object, while independent per-view edits are averaged into a haze. Three
measurements (`metrics.solidity`), each per view (or view pair) with a bootstrap interval, so
that two edits are compared by whether their intervals overlap:

  fit              PSNR of the edited NeRF's renders at the views it learned the edit from
                   (`propagation.edited_views`) against their edited images, inside the masks;
  solidity         at held-out cameras, the edited NeRF's opacity inside the selection's box
                   (its lowest `support_clearance` along the up axis left out: the surface the
                   object stands on is not the object) against the proxy's visible silhouette:
                   IoU of (opacity > threshold) and the mean opacity inside the silhouette
                   (figure: evaluation/solidity.png);
  correspondences  verified correspondences (`metrics.consistency` with the
                   `correspondence_matcher`, tracked by default; epipolar inliers) between
                   renders of the edited NeRF at neighbouring held-out cameras, rendered at
                   `correspondence_size` px, against the original NeRF's renders of the same
                   cameras: the counts, the relative change and its interval over view pairs.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from signerf_jax import camera as camera_lib
from signerf_jax import files
from signerf_jax.editing import figures
from signerf_jax.editing.config import NerfConsistencySettings
from signerf_jax.editing.stages.context import EditContext, evenly_spaced
from signerf_jax.editing.stages.propagation import EditedViews
from signerf_jax.geometry import reference_cameras
from signerf_jax.metrics import consistency, solidity
from signerf_jax.nerf import render


def opacity_box(bounds: np.ndarray, up: np.ndarray, clearance: float) -> np.ndarray:
  """[2, 3] the box `bounds` with its lowest `clearance` of the height along the axis nearest
  to `up` removed."""
  box = np.array(bounds, np.float64)
  axis = int(np.argmax(np.abs(up)))
  lift = clearance * (box[1, axis] - box[0, axis])
  if up[axis] >= 0:
    box[0, axis] += lift
  else:
    box[1, axis] -= lift
  return box


def _summary(values: np.ndarray, settings: NerfConsistencySettings) -> dict[str, Any]:
  """`solidity.summarize` and the values themselves (None for a view not measured)."""
  return {**solidity.summarize(values, **settings.bootstrap()),
          "per_view": [None if np.isnan(value) else float(value) for value in values]}


def _fit(nerf, views: EditedViews, settings: NerfConsistencySettings) -> dict[str, Any]:
  inside = np.asarray(views.conditioning.mask) > 0
  renders = render.render_cameras(nerf.model, nerf.variables, views.cameras, pixels=inside)["rgb"]
  per_view = solidity.masked_psnr(renders, views.edited, inside)
  return _summary(per_view, settings)


def _solidity(context: EditContext, nerf, silhouettes: np.ndarray,
              settings: NerfConsistencySettings) -> dict[str, Any]:
  """The solidity summaries; writes evaluation/solidity.png (per held-out view, the render and
  the opacity inside the box, the proxy's silhouette outlined)."""
  box = opacity_box(context.selection.bounds,
                    np.asarray(reference_cameras.scene_up(context.dataset.cameras)),
                    settings.support_clearance)
  renders = render.render_cameras(nerf.model, nerf.variables, context.eval_cameras,
                                  selection_box=box)
  opacity = renders["selection_weight"]
  files.write_image(context.directory.path("evaluation", "solidity.png"), figures.image_grid(
      [[figures.outline(image, silhouette) for image, silhouette in zip(images, silhouettes)]
       for images in (renders["rgb"], opacity)],
      [["edited NeRF"] * len(opacity), ["opacity in the box"] * len(opacity)]))
  per_view = solidity.solidity(opacity, silhouettes, settings.opacity_threshold)
  return {name: _summary(values, settings) for name, values in per_view.items()}


def _selection_rectangles(cameras: camera_lib.Cameras, points: np.ndarray) -> np.ndarray:
  """[N, H, W] bool: the rectangle around the selection's projection in each camera."""
  pixels, z_depth = (np.asarray(array) for array in camera_lib.project(cameras, points))
  masks = np.zeros((cameras.num_cameras, cameras.height, cameras.width), bool)
  for index, (projected, depth) in enumerate(zip(pixels, z_depth)):
    finite = projected[np.all(np.isfinite(projected), axis=-1) & (depth > 0)]
    if len(finite):
      x0, y0 = np.clip(np.floor(finite.min(0)).astype(int), 0, [cameras.width, cameras.height])
      x1, y1 = np.clip(np.ceil(finite.max(0)).astype(int), 0, [cameras.width, cameras.height])
      masks[index, y0:y1, x0:x1] = True
  return masks


def _correspondences(context: EditContext, original, edited,
                     settings: NerfConsistencySettings) -> dict[str, Any]:
  cameras = context.eval_cameras
  cameras = cameras.take(evenly_spaced(np.arange(cameras.num_cameras),
                                       settings.correspondence_views))
  scale = settings.correspondence_size / max(cameras.width, cameras.height)
  cameras = cameras.resized(max(1, round(cameras.width * scale)),
                            max(1, round(cameras.height * scale)))
  masks = _selection_rectangles(cameras, context.selection.points)
  matching = dataclasses.replace(context.settings.consistency,
                                 matcher=settings.correspondence_matcher)
  reports = {name: consistency.image_set_consistency(
      render.render_cameras(nerf.model, nerf.variables, cameras)["rgb"], cameras, masks,
      matching) for name, nerf in (("original", original), ("edited", edited))}
  counts = {name: np.array([pair.epipolar_inliers for pair in report.pairs], np.float64)
            for name, report in reports.items()}
  return {"matcher": matching.matcher, "size": [cameras.width, cameras.height],
          "views": cameras.num_cameras,
          "pairs": len(counts["edited"]),
          "mean_epipolar_inliers": {name: float(np.mean(values)) if len(values) else None
                                    for name, values in counts.items()},
          "relative_change": consistency.relative_change(
              reports["edited"], reports["original"])["mean_epipolar_inliers"],
          "interval": list(solidity.relative_change_interval(
              counts["edited"], counts["original"], **settings.bootstrap()))
                      if len(counts["edited"]) else None}


def measure(context: EditContext, views: EditedViews, original, edited, silhouettes: np.ndarray,
            settings: NerfConsistencySettings) -> dict[str, Any]:
  """fit (to `views`, the edited images it learned), solidity ({iou, mean_opacity}) and
  correspondences of the edited NeRF (see the module docstring); `silhouettes` [N, H, W] bool
  are the proxy's at the held-out cameras."""
  return {"fit_psnr": _fit(edited, views, settings),
          "solidity": _solidity(context, edited, silhouettes, settings),
          "correspondences": _correspondences(context, original, edited, settings)}
