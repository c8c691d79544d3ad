"""Prompt and shape adherence of single views (gates 1 and 2 of `evaluation`).

Each single view is generated at every ControlNet scale with one key, so only the scale differs;
the generated object is found by its difference from the VAE round trip of the object-free view
(`generated_objects.segment_objects`). Shape adherence is the IoU of that object with the true
silhouette per scale; prompt adherence, at scale 1, whether its dominant colour is the one the
caption names. Beside them (not gates): the same segmentation of the VAE round trip of the true
renders (the IoU a perfect generator would reach: `segmentation_ceiling_iou`; for colours,
`vae_ceiling`), where the IoU is lost (pooled precision and recall, and the share of masked
ground pixels off by more than the threshold), the IoU with the pipeline's own proxy masks
(`with_proxy_masks`: the silhouette dilated and feathered as `SelectionConfig` does for a proxy
by default, about 3 pixels at 64; the paper inpaints the visible proxy, "further dilated", while
the gate's boxes leave the whole shape to the depth), and, in both kinds of mask, with the object
found by its caption's hue (`generated_objects.segment_by_hue`, views whose caption names a
chromatic colour), which does not count the repainted ground around the object.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from signerf_jax.default_model import captions as captions_lib
from signerf_jax.default_model import generated_objects
from signerf_jax.default_model import samples
from signerf_jax.default_model.evaluation import FULL_SCALE, EvaluationSettings
from signerf_jax.default_model.evaluation_generation import (CallTimer, ViewInputs,
                                                             evaluation_key,
                                                             generate_with_captions,
                                                             pipeline_proxy_masks,
                                                             round_trip, with_scale)
from signerf_jax.editing import evaluation as editing_evaluation
from signerf_jax.editing.generation import Generator
from signerf_jax.metrics import colors
from signerf_jax.metrics import silhouettes as silhouettes_lib


@dataclasses.dataclass(frozen=True)
class SingleViews:
  """The single views without their view axis, and what their generations are compared with.

  Attributes:
    captions: S captions.
    background: [S, H, W, 3] the object-free views in [0, 1] (what is inpainted).
    reference: [S, H, W, 3] their VAE round trip (what the generated objects differ from).
    masks: [S, H, W] the box inpainting masks.
    controls: [S, H, W] the control depth.
    silhouettes: [S, H, W] bool, the true object silhouettes.
    truth_round_trip: [S, H, W, 3] the VAE round trip of the true renders.
    keys: [S, 2] key data, one per view (the same at every ControlNet scale).
  """

  captions: list[str]
  background: np.ndarray
  reference: np.ndarray
  masks: np.ndarray
  controls: np.ndarray
  silhouettes: np.ndarray
  truth_round_trip: np.ndarray
  keys: np.ndarray

  @classmethod
  def from_views(cls, generator: Generator, views: ViewInputs, seed: int) -> "SingleViews":
    """The single views ([S, 1, ...]) of `views`, the round trips by `generator`'s VAE."""
    background, masks, controls, silhouettes, truth = (
        array[:, 0] for array in (views.background, views.masks, views.controls,
                                  views.silhouettes, views.truth))
    keys = np.stack([evaluation_key(seed, "single", index)
                     for index in range(len(views.captions))])
    return cls(captions=views.captions, background=background,
               reference=round_trip(generator, background), masks=masks, controls=controls,
               silhouettes=silhouettes, truth_round_trip=round_trip(generator, truth), keys=keys)


def _segment(images: np.ndarray, singles: SingleViews, inpainting_masks: np.ndarray,
             settings: EvaluationSettings) -> np.ndarray:
  """[S, H, W] bool: the objects in [S, H, W, 3] `images` inpainted under `inpainting_masks`."""
  return generated_objects.segment_objects(images, singles.reference, inpainting_masks,
                                           settings.difference_threshold,
                                           settings.min_component_pixels)


def _shape_measures(generated: list[np.ndarray], objects: list[np.ndarray], singles: SingleViews,
                    inpainting_masks: np.ndarray, settings: EvaluationSettings) -> dict:
  """Per ControlNet scale: mean and median IoU, where the IoU is lost (pooled precision and
  recall, the repainted ground that differs from the original) and views without an object;
  "per_view": the [S] IoUs of each scale."""
  ious = [silhouettes_lib.silhouette_iou(found, singles.silhouettes) for found in objects]
  precision_recall = [silhouettes_lib.pooled_precision_recall(found, singles.silhouettes)
                      for found in objects]
  return {
      "mean_iou": [float(np.mean(values)) for values in ious],
      "median_iou": [float(np.median(values)) for values in ious],
      "pooled_precision": [precision for precision, _ in precision_recall],
      "pooled_recall": [recall for _, recall in precision_recall],
      "changed_ground_share": [
          generated_objects.changed_ground_share(images, singles.reference, inpainting_masks,
                                                 singles.silhouettes,
                                                 settings.difference_threshold)
          for images in generated],
      "no_object_found": [int(np.sum(~found.any((1, 2)))) for found in objects],
      "per_view": ious}


def _sweep(generator: Generator, singles: SingleViews, inpainting_masks: np.ndarray,
           settings: EvaluationSettings, timer: CallTimer
           ) -> tuple[list[np.ndarray], list[np.ndarray], dict]:
  """Generations ([S, H, W, 3]) and found objects ([S, H, W]) per ControlNet scale under
  `inpainting_masks` ([S, H, W]), and their `_shape_measures`."""
  generated, objects = [], []
  for scale in settings.controlnet_scales:
    generated.append(generate_with_captions(
        with_scale(generator, scale), singles.captions, singles.background, inpainting_masks,
        singles.controls, singles.keys, timer, "single_view"))
    objects.append(_segment(generated[-1], singles, inpainting_masks, settings))
  return generated, objects, _shape_measures(generated, objects, singles, inpainting_masks,
                                             settings)


def _segmentation_ceiling(singles: SingleViews, inpainting_masks: np.ndarray,
                          settings: EvaluationSettings) -> float:
  """Mean IoU of the objects segmented in the VAE round trip of the true renders."""
  return float(np.mean(silhouettes_lib.silhouette_iou(
      _segment(singles.truth_round_trip, singles, inpainting_masks, settings),
      singles.silhouettes)))


def _by_caption_hue(generated: list[np.ndarray], singles: SingleViews,
                    inpainting_masks: np.ndarray, settings: EvaluationSettings) -> dict:
  """Shape adherence with the objects found by their caption's hue inside `inpainting_masks`
  ([S, H, W], those `generated` was inpainted under), over the views whose caption names a
  chromatic colour: "mean_iou" per scale and its "segmentation_ceiling_iou" (NaN without such
  views)."""
  named_colors = [captions_lib.parse_caption(caption).color for caption in singles.captions]
  hue_views = [index for index, color in enumerate(named_colors)
               if color in colors.CHROMATIC_COLORS]

  def hue_iou(images: np.ndarray) -> float:
    if not hue_views:
      return float("nan")
    found = generated_objects.segment_by_hue(images[hue_views], inpainting_masks[hue_views],
                                             [named_colors[index] for index in hue_views],
                                             settings.min_component_pixels)
    return float(np.mean(silhouettes_lib.silhouette_iou(found, singles.silhouettes[hue_views])))

  return {"samples": len(hue_views), "mean_iou": [hue_iou(images) for images in generated],
          "segmentation_ceiling_iou": hue_iou(singles.truth_round_trip)}


def _prompt_adherence(singles: SingleViews, generated: np.ndarray, objects: np.ndarray) -> dict:
  """Gate 1 over the views whose caption names a colour, from their generations at FULL_SCALE
  ([S, H, W, 3]) and found objects ([S, H, W]): the share in the named colour, per colour, the
  views without an object (misses) and the share the VAE round trip keeps (`vae_ceiling`)."""
  by_color: dict[str, list[bool]] = {}
  kept_by_vae = []
  missing = 0
  for index, caption in enumerate(singles.captions):
    adherence = editing_evaluation.prompt_color_adherence(
        caption, generated[index][None], objects[index][None])
    named = captions_lib.parse_caption(caption).color
    if named is not None:
      missing += adherence is None
      by_color.setdefault(named, []).append(adherence is not None and adherence["share"] == 1.0)
      kept = editing_evaluation.prompt_color_adherence(
          caption, singles.truth_round_trip[index][None], singles.silhouettes[index][None])
      kept_by_vae.append(kept is not None and kept["share"] == 1.0)
  hits = [hit for values in by_color.values() for hit in values]
  return {
      "samples": len(hits), "controlnet_scale": FULL_SCALE,
      "share": float(np.mean(hits)) if hits else float("nan"),
      "per_color": {color: float(np.mean(values)) for color, values in sorted(by_color.items())},
      "no_object_found": int(missing),
      "vae_ceiling": float(np.mean(kept_by_vae)) if kept_by_vae else float("nan")}


def evaluate_singles(generator: Generator, views: ViewInputs, settings: EvaluationSettings,
                     timer: CallTimer) -> tuple[dict, dict]:
  """Prompt adherence (views whose caption names a colour) and shape adherence (all views).

  Args:
    generator: the single views' generator (`settings.singles_per_device`).
    views: single views ([S, 1, ...]).
  Returns:
    ({"prompt_adherence", "shape_adherence"} measures,
     {"generated": [scales, S, H, W, 3], "objects": [scales, S, H, W] bool}).
  """
  singles = SingleViews.from_views(generator, views, settings.seed)
  generated, objects, shape = _sweep(generator, singles, singles.masks, settings, timer)
  # Not a gate: the same with the pipeline's own proxy-placement masks (the visible proxy,
  # dilated and feathered as `SelectionConfig` does by default), as the paper inpaints.
  proxy_masks = pipeline_proxy_masks(singles.silhouettes, settings)
  proxy_generated, _, with_proxy_masks = _sweep(generator, singles, proxy_masks, settings,
                                                timer)
  with_proxy_masks.pop("per_view")
  full = list(settings.controlnet_scales).index(FULL_SCALE)
  kinds = {kind: views.view_kinds[:, 0] == code for code, kind in enumerate(samples.VIEW_KINDS)}
  return {
      "prompt_adherence": _prompt_adherence(singles, generated[full], objects[full]),
      "shape_adherence": {
          "samples": len(views.captions), "controlnet_scales": list(settings.controlnet_scales),
          **{name: values for name, values in shape.items() if name != "per_view"},
          "mean_iou_by_view_kind": {kind: [float(np.mean(values[chosen]))
                                           for values in shape["per_view"]]
                                    for kind, chosen in kinds.items() if chosen.any()},
          "segmentation_ceiling_iou": _segmentation_ceiling(singles, singles.masks, settings),
          "with_proxy_masks": {
              "dilation": settings.proxy_mask_dilation, "feather": settings.proxy_mask_feather,
              **with_proxy_masks,
              "segmentation_ceiling_iou": _segmentation_ceiling(singles, proxy_masks, settings),
              "by_caption_hue": _by_caption_hue(proxy_generated, singles, proxy_masks,
                                                settings)},
          "by_caption_hue": _by_caption_hue(generated, singles, singles.masks, settings)},
  }, {"generated": np.stack(generated), "objects": np.stack(objects)}
