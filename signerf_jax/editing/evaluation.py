"""Measuring an edit: background preservation, multi-view consistency, CLIP directional
similarity, and adherence to the prompt's colour and the proxy's shape.

* Background preservation (paper, appendix "Metrics"): renders of the original and the edited
  NeRF from held-out cameras, compared outside the selection's inpainting mask
  (`metrics.background`: the paper's PSNR_bg / SSIM_bg and background-only variants).
* Consistency (paper, appendix "Multiview Consistency"): verified SIFT correspondences between
  neighbouring views (`metrics.consistency`) of the original images, of the sheet-propagated edit
  and of independent per-view edits (each view inpainted on its own with the same prompt and
  seed, `independent_edits`), and their change relative to the original images.
* CLIP text-image directional similarity (`clip.similarity`) of the image edit and of
  the NeRF renders, when CLIP weights are given.
* Prompt colour adherence: the share of views whose edited region's dominant colour
  (`metrics.colors.dominant_color`) is the colour the prompt names (when it names one
  of the shipped model's palette colours).
* Shape adherence (proxy selections): IoU between the pixels the edit changed and the proxy's
  visible silhouette.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from signerf_jax import camera as camera_lib
from signerf_jax.clip import word_tokenizer
from signerf_jax.editing import sheet as sheet_lib
from signerf_jax.editing.generation import Generator
from signerf_jax.editing.update import SlotViews, independent_batch
from signerf_jax.metrics import colors, consistency, silhouettes

# A pixel counts as changed by the edit when its colour moved by more than this (mean over RGB).
CHANGE_THRESHOLD = 0.1


def independent_edits(generator: Generator, layout: sheet_lib.SheetLayout, views: SlotViews,
                      keys) -> np.ndarray:
  """Each view inpainted on its own (`update.independent_batch`), in batches.

  Returns:
    [n, H, W, 3] float32.
  """
  edited = []
  for start in range(0, len(keys), generator.batch_size):
    part = slice(start, start + generator.batch_size)
    batch = SlotViews(views.images[part], views.masks[part], views.controls[part],
                      views.boxes[part])
    edited.append(independent_batch(generator, layout, batch, keys[part])[0])
  return np.concatenate(edited)


def consistency_comparison(image_sets: dict[str, np.ndarray], cameras: camera_lib.Cameras,
                           masks: np.ndarray, settings: consistency.ConsistencySettings
                           ) -> dict[str, Any]:
  """Verified correspondences of each image set (same views, cameras and keypoint masks), and
  the relative change of every set against the "original" one."""
  reports = {name: consistency.image_set_consistency(images, cameras, masks, settings)
             for name, images in image_sets.items()}
  result = {name: report.summary() for name, report in reports.items()}
  result["relative_to_original"] = {
      name: consistency.relative_change(report, reports["original"])
      for name, report in reports.items() if name != "original"}
  return result


def prompt_color_adherence(prompt: str, images: np.ndarray, selected: np.ndarray
                           ) -> dict[str, Any] | None:
  """Share of views whose selected pixels' dominant colour is the prompt's colour (None when the
  prompt names no palette colour or no view has selected pixels)."""
  color = colors.named_color(word_tokenizer.split_words(prompt))
  views = [index for index in range(len(images)) if selected[index].any()]
  if color is None or not views:
    return None
  found = [colors.dominant_color(images[index][selected[index]]) for index in views]
  return {"color": color, "share": float(np.mean([name == color for name in found])),
          "dominant_colors": found}


def shape_adherence(original: np.ndarray, edited: np.ndarray, selected: np.ndarray,
                    masks: np.ndarray) -> float | None:
  """Mean IoU over views between the changed pixels (inside the inpainting mask) and the
  proxy's visible silhouette `selected`; None when no view shows the proxy."""
  changed = (np.mean(np.abs(edited - original), axis=-1) > CHANGE_THRESHOLD) & (masks > 0)
  shown = np.any(selected, axis=(1, 2))
  if not shown.any():
    return None
  return float(np.mean(silhouettes.silhouette_iou(changed[shown], selected[shown])))
