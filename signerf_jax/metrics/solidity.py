"""Does the edited NeRF hold a solid, consistent object? Measured on the NeRF itself.

The paper's claim (Sec. 3): images made consistent through the reference sheet can be fitted by
one radiance field, which then converges to a crisp object; inconsistent per-view edits are
averaged into a haze. Two per-view measurements answer it, and a bootstrap over views says
whether two edits differ:

  fit        PSNR (dB) of the fine-tuned NeRF's renders at the training cameras against the
             edited images it was trained on, inside the selection: consistent images can be
             fitted, inconsistent ones cannot.
  solidity   at held-out cameras, the NeRF's opacity inside the selection (the render weight of
             its samples there, `nerf.render`'s "selection_weight") against the proxy's visible
             silhouette: the IoU of (opacity > threshold) with the silhouette, and the mean
             opacity inside the silhouette (1: solid; a haze stays well below).
  bootstrap  a percentile interval of the mean of per-view values (or of the relative change of
             per-pair correspondence counts), resampling views (pairs) with replacement: two
             edits separate when their intervals do not overlap. Two edits measured at the same
             views are also compared view by view (`paired_difference`): the interval of the
             mean difference leaves out zero when one is consistently above the other, even
             where the spread from view to view makes their own intervals overlap.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from signerf_jax.errors import InputError
from signerf_jax.metrics import image as image_metrics
from signerf_jax.metrics import silhouettes

OPACITY_THRESHOLD = 0.5
# An exact fit: `metrics.image.psnr` floors the squared error at 1e-10 (data range 1).
MAX_PSNR_DB = 100.0


def masked_psnr(renders: np.ndarray, targets: np.ndarray, masks: np.ndarray) -> np.ndarray:
  """[N] PSNR (dB) per view inside the masks; NaN for a view whose mask is empty.

  Args:
    renders, targets: [N, H, W, 3] in [0, 1].
    masks: [N, H, W], non-zero where the view is compared.
  """
  renders, targets = np.asarray(renders, np.float64), np.asarray(targets, np.float64)
  if renders.shape != targets.shape or renders.shape[:3] != np.shape(masks):
    raise InputError(f"renders {renders.shape}, targets {targets.shape} and masks "
                     f"{np.shape(masks)} must have the same views and pixels", field="masks")
  inside = np.asarray(masks) > 0
  psnr = [float(image_metrics.psnr_jit(render, target, mask)) if mask.any() else np.nan
          for render, target, mask in zip(renders, targets, inside)]
  return np.asarray(psnr)


def solidity(opacity: np.ndarray, silhouettes_shown: np.ndarray,
             threshold: float = OPACITY_THRESHOLD) -> dict[str, np.ndarray]:
  """Per-view solidity of an object against the silhouette it should have.

  Args:
    opacity: [N, H, W] in [0, 1], the NeRF's render weight inside the selection.
    silhouettes_shown: [N, H, W] bool, the proxy's visible silhouette.
    threshold: opacity above which a pixel counts as the object.
  Returns:
    iou [N] of (opacity > threshold) with the silhouette, and mean_opacity [N] inside the
    silhouette; both NaN for views that do not show the silhouette.
  """
  opacity, shown = np.asarray(opacity, np.float64), np.asarray(silhouettes_shown, bool)
  if opacity.shape != shown.shape or opacity.ndim != 3:
    raise InputError(f"opacity {opacity.shape} and silhouettes {shown.shape} must both be "
                     "[N, H, W]", field="silhouettes")
  if not 0 < threshold < 1:
    raise InputError(f"must be in (0, 1), got {threshold}", field="threshold")
  counts = shown.sum(axis=(1, 2))
  iou = silhouettes.silhouette_iou(opacity > threshold, shown)
  mean_opacity = np.sum(np.where(shown, opacity, 0.0), axis=(1, 2)) / np.maximum(counts, 1)
  visible = counts > 0
  return {"iou": np.where(visible, iou, np.nan), "mean_opacity": np.where(visible, mean_opacity,
                                                                         np.nan)}


def bootstrap_interval(values: np.ndarray, num_resamples: int = 2000, confidence: float = 0.95,
                       seed: int = 0, statistic=None) -> tuple[float, float]:
  """Percentile bootstrap interval of a statistic of `values`, resampling its rows.

  Args:
    values: [N] per-view values, or [N, K] rows resampled together (e.g. a pair's counts in two
      image sets); rows holding a NaN are left out.
    statistic: [R, N(, K)] resampled values -> [R] estimates; default the mean over N.
  Returns:
    (low, high); one row gives a zero-width interval.
  Raises:
    InputError when no row is left.
  """
  values = np.asarray(values, np.float64)
  values = values[~np.isnan(values.reshape(len(values), -1)).any(axis=1)]
  if values.shape[0] == 0:
    raise InputError("no values to bootstrap (every view was empty)", field="values")
  if not 0 < confidence < 1:
    raise InputError(f"must be in (0, 1), got {confidence}", field="confidence")
  rng = np.random.default_rng(seed)
  resampled = values[rng.integers(0, len(values), size=(num_resamples, len(values)))]
  estimates = np.mean(resampled, axis=1) if statistic is None else statistic(resampled)
  tail = 100 * (1 - confidence) / 2
  low, high = np.percentile(estimates, [tail, 100 - tail])
  return float(low), float(high)


def relative_change_interval(edited: np.ndarray, original: np.ndarray, **bootstrap_options
                             ) -> tuple[float, float]:
  """Bootstrap interval over view pairs of sum(edited) / sum(original) - 1, e.g. verified
  correspondences per pair after an edit against before it (-0.7: 70% fewer)."""
  pairs = np.stack([np.asarray(edited, np.float64), np.asarray(original, np.float64)], axis=1)
  return bootstrap_interval(
      pairs, statistic=lambda rows: rows[..., 0].sum(1) / np.maximum(rows[..., 1].sum(1), 1e-12)
      - 1, **bootstrap_options)


def summarize(values: np.ndarray, **bootstrap_options) -> dict[str, Any]:
  """mean, bootstrap interval ([low, high]) and count of per-view values (NaNs left out)."""
  values = np.asarray(values, np.float64)
  known = values[~np.isnan(values)]
  return {"mean": float(np.mean(known)) if known.size else None,
          "interval": list(bootstrap_interval(known, **bootstrap_options)) if known.size else None,
          "count": int(known.size)}


def paired_difference(minuend: Sequence[float | None], subtrahend: Sequence[float | None],
                      **bootstrap_options) -> dict[str, Any]:
  """The view-by-view difference of two measurements at the same views.

  Args:
    minuend, subtrahend: [N] per-view values, NaN or None where a view was not measured; views
      missing from either are left out.
  Returns:
    `summarize` of minuend - subtrahend (mean, interval, count) and "significant": whether the
    interval leaves out zero.
  Raises:
    InputError when the two do not hold the same number of views.
  """
  as_array = lambda values: np.array([np.nan if value is None else value for value in values],
                                     np.float64)
  minuend, subtrahend = as_array(minuend), as_array(subtrahend)
  if minuend.shape != subtrahend.shape or minuend.ndim != 1:
    raise InputError(f"{minuend.shape} and {subtrahend.shape} views: a paired difference needs "
                     "the same views measured twice", field="per_view")
  summary = summarize(minuend - subtrahend, **bootstrap_options)
  interval = summary["interval"]
  return {**summary, "significant": interval is not None and (interval[0] > 0 or interval[1] < 0)}


def compare(first: dict[str, Any], second: dict[str, Any]) -> str:
  """Where the first `summarize` result's interval lies against the second's: "higher" (wholly
  above), "lower" (wholly below) or "overlapping" (also when either was not measured)."""
  if first["interval"] is None or second["interval"] is None:
    return "overlapping"
  (low_a, high_a), (low_b, high_b) = first["interval"], second["interval"]
  return "higher" if low_a > high_b else "lower" if high_a < low_b else "overlapping"
