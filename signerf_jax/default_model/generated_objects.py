"""The generated object in an inpainted view, and how alike objects' colours are (numpy).

Segmenting the generated object. Inside the inpainting mask (where the model regenerated
everything, object and ground), a pixel belongs to the object when its colour differs in some
channel by more than a threshold (`EvaluationSettings.difference_threshold`) from the *VAE round
trip* of the object-free view (`evaluation_generation.vae_round_trip`: encode, take the posterior
mode, decode). Comparing with the round trip rather than the exact background cancels what the
VAE alone loses (blurred ground textures, slight colour shifts), which every generated pixel goes
through too. Then connected components (4-connected) smaller than `min_component_pixels` are
dropped (isolated specks of regenerated texture) and holes smaller than that are filled (object
pixels that happen to match the ground). Only area, not morphological opening, is used: opening
also erases the thin parts (legs, handles) of the small objects of 64-pixel views, which costs
about 5 IoU points on the true renders, against under 1 for this. Applied to the VAE round trip
of the true renders, the segmentation gives the shape IoU a perfect generator would reach.

The object found by its caption's hue (`segment_by_hue`, views whose caption names a chromatic
colour): the masked pixels whose hue is nearest that colour's (`metrics.colors.pixel_hue_colors`),
cleaned the same way. Repainted ground and background rarely take the object's hue, so this
measures the object's own silhouette where the difference segmentation also counts a hazy
repaint of the box as object.

Colours: each object's dominant palette colour and mean colour (`object_colors`), and over pairs
of objects the share with the same colour name (`color_agreement`) and the mean distance of
their mean colours (`mean_color_distance`).
"""

from __future__ import annotations

import itertools
from typing import Sequence

import numpy as np

from signerf_jax.errors import InputError
from signerf_jax.metrics import colors
from signerf_jax.metrics import silhouettes as silhouettes_lib


def segment_objects(generated: np.ndarray, reference: np.ndarray, masks: np.ndarray,
                    difference_threshold: float, min_component_pixels: int) -> np.ndarray:
  """The generated objects (module docstring).

  Args:
    generated: [N, H, W, 3] generated images in [0, 1].
    reference: [N, H, W, 3] the object-free views (as the VAE reproduces them) in [0, 1].
    masks: [N, H, W] inpainting masks (>= 0.5: regenerated).
    difference_threshold: largest channel difference still counted as background.
    min_component_pixels: smaller components are dropped and smaller holes filled.
  Returns:
    [N, H, W] bool.
  """
  inside = np.asarray(masks) >= 0.5
  changed = (np.abs(np.asarray(generated, np.float32) - np.asarray(reference, np.float32)).max(-1)
             > difference_threshold) & inside
  return silhouettes_lib.without_specks(changed, min_component_pixels) & inside


def segment_by_hue(generated: np.ndarray, masks: np.ndarray, caption_colors: Sequence[str],
                   min_component_pixels: int) -> np.ndarray:
  """The generated objects as the masked pixels of their caption's hue (module docstring).

  Args:
    generated: [N, H, W, 3] in [0, 1]; masks: [N, H, W] (>= 0.5: regenerated).
    caption_colors: N chromatic palette colour names (`colors.CHROMATIC_COLORS`).
    min_component_pixels: smaller components are dropped, smaller holes filled.
  Returns:
    [N, H, W] bool.
  """
  chromatic, nearest = colors.pixel_hue_colors(generated)
  named = np.asarray([colors.CHROMATIC_COLORS.index(color) for color in caption_colors])
  inside = np.asarray(masks) >= 0.5
  return silhouettes_lib.without_specks(chromatic & (nearest == named[:, None, None]) & inside,
                                        min_component_pixels) & inside


def changed_ground_share(generated: np.ndarray, reference: np.ndarray, masks: np.ndarray,
                         silhouettes: np.ndarray, difference_threshold: float) -> float:
  """Share of the masked pixels off the true object (the ground and background the model
  repaints) that differ from `reference` by more than the threshold in some channel: what the
  segmentation would count as object there before dropping specks (NaN without such pixels)."""
  ground = (np.asarray(masks) >= 0.5) & ~np.asarray(silhouettes, bool)
  difference = np.abs(np.asarray(generated, np.float32) - np.asarray(reference, np.float32))
  changed = difference.max(-1) > difference_threshold
  return float(changed[ground].mean()) if ground.any() else float("nan")


def object_colors(images: np.ndarray, objects: np.ndarray) -> tuple[list[str | None], np.ndarray]:
  """Each object's dominant palette colour and mean colour.

  Args:
    images: [N, H, W, 3] in [0, 1]; objects: [N, H, W] bool.
  Returns:
    (N names, None for an empty object; [N, 3] mean RGB, NaN for an empty object).
  """
  names, means = [], []
  for image, pixels in zip(np.asarray(images, np.float32), np.asarray(objects, bool)):
    empty = not pixels.any()
    names.append(None if empty else colors.dominant_color(image[pixels]))
    means.append(np.full(3, np.nan) if empty else image[pixels].mean(0))
  return names, np.stack(means)


def _pairs(count: int, against_count: int | None) -> list[tuple[int, int]]:
  """Index pairs: every unordered pair of `count` items, or every (item, other) pair."""
  if against_count is None:
    return list(itertools.combinations(range(count), 2))
  return list(itertools.product(range(count), range(against_count)))


def color_agreement(colors: Sequence[str | None], against: Sequence[str | None] | None = None
                    ) -> float:
  """Share of pairs with the same colour name: the pairs within `colors`, or every pair of one
  of `colors` and one of `against`. A missing object (None) agrees with nothing."""
  others = colors if against is None else against
  pairs = _pairs(len(colors), None if against is None else len(against))
  if not pairs:
    raise InputError("no pairs to compare: need two colours, or one and one to compare against",
                     field="colors")
  return float(np.mean([colors[i] is not None and colors[i] == others[j] for i, j in pairs]))


def mean_color_distance(means: np.ndarray, against: np.ndarray | None = None) -> float:
  """Mean Euclidean RGB distance over the pairs `color_agreement` takes ([N, 3] / [M, 3] mean
  colours; pairs with a missing object, NaN, are skipped; NaN when none is left)."""
  others = means if against is None else against
  distances = [np.linalg.norm(means[i] - others[j])
               for i, j in _pairs(len(means), None if against is None else len(against))]
  distances = [distance for distance in distances if np.isfinite(distance)]
  return float(np.mean(distances)) if distances else float("nan")
