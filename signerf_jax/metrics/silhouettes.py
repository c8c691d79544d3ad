"""Silhouette metrics on [N, H, W] boolean masks: intersection over union per view, pooled
precision and recall, and the clean-up of segmentations (specks dropped, small holes filled).

Used to measure shape adherence: of the generated objects against the proxy's silhouette (the
edit's evaluation) and of the shipped model's objects against the true ones.
"""

from __future__ import annotations

import cv2
import numpy as np


def silhouette_iou(predicted: np.ndarray, target: np.ndarray) -> np.ndarray:
  """[N] intersection over union of [N, H, W] boolean silhouettes (1 where both are empty)."""
  predicted, target = np.asarray(predicted, bool), np.asarray(target, bool)
  union = np.sum(predicted | target, axis=(1, 2))
  return np.where(union > 0, np.sum(predicted & target, axis=(1, 2)) / np.maximum(union, 1), 1.0)


def pooled_precision_recall(predicted: np.ndarray, target: np.ndarray) -> tuple[float, float]:
  """(precision, recall) of [N, H, W] boolean silhouettes, pixels pooled over all views (NaN
  when nothing is predicted or nothing is to be found)."""
  predicted, target = np.asarray(predicted, bool), np.asarray(target, bool)
  hits = float(np.sum(predicted & target))
  ratio = lambda total: hits / total if total else float("nan")
  return ratio(float(predicted.sum())), ratio(float(target.sum()))


def keep_components(binary: np.ndarray, min_pixels: int) -> np.ndarray:
  """[H, W] bool: the 4-connected components of `binary` with at least `min_pixels` pixels."""
  _, labels, stats, _ = cv2.connectedComponentsWithStats(binary.astype(np.uint8), connectivity=4)
  keep = stats[:, cv2.CC_STAT_AREA] >= min_pixels
  keep[0] = False  # Label 0 is the zero pixels.
  return keep[labels]


def without_specks(views: np.ndarray, min_pixels: int) -> np.ndarray:
  """[N, H, W] bool views with components smaller than `min_pixels` dropped and holes smaller
  than that filled."""
  cleaned = []
  for view in views:
    view = keep_components(view, min_pixels)
    cleaned.append(view | (~view & ~keep_components(~view, min_pixels)))
  return np.stack(cleaned)
