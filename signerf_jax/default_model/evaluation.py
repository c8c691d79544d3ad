"""The default model's quality gates (issue 5): what is measured, how, and the thresholds.

Every generation inpaints the object-free view (`background_rgb`) under the object's "box" mask
(`batches.box_masks`: its silhouette's bounding box plus a margin, so only position and extent are
given and the shape has to come from the control depth), with the stored control depth and the
sample's caption, starting from noise (`evaluation_generation`):

1. Prompt adherence: single views whose caption names a colour, at ControlNet scale 1; a view
   passes when the dominant colour (`metrics.colors.dominant_color`) of its generated object's pixels
   is the caption's colour (`editing.evaluation.prompt_color_adherence`). No object: a miss.
   Its ceiling (`vae_ceiling`): the share of the same views whose true render keeps its colour
   through the VAE round trip (what a perfect denoiser can reach through this VAE).
2. Shape adherence: the same single views at every ControlNet scale, each view with one key at
   all scales (so only the scale differs); the IoU of the generated object's silhouette with the
   true one. The gate: IoU at scale 1 >= the threshold and rising with the scale.
   (1 and 2: `evaluation_singles`.)
3. Consistency with an unspecified colour: sheets whose caption names no colour. Per sheet,
   the dominant colours of
     * the 5 tiles of the generated reference sheet (the slot empty, as the pipeline makes it),
     * the same 5 views each generated alone (a single tile, its own key), and
     * the slot update: the held-out 6th view (stored last) in the slot of that fixed sheet,
       only the slot inpainted (`sheet.slot_update_inputs`);
   and their agreement: the share of view pairs with the same dominant colour among the sheet's
   tiles (10 pairs), among the independent views (10 pairs), and between the slot and each
   tile (5 pairs). The mean distance between the objects' mean RGB colours over the same pairs
   is reported beside it. The gate: the sheet's and the slot's agreement each exceed the
   independent views' by at least a margin (`evaluation_consistency`).
4. The control steers the shape (issue 19): the single views of 2 inpainted under the
   pipeline's own proxy masks instead (the silhouette dilated and feathered as `SelectionConfig`
   does), the object found by its caption's hue (views naming a chromatic colour), which does
   not count the ground repainted around it. The gate: IoU at scale 1 >= a threshold and a rise
   from scale 0 >= another (`control_gate`).
5. Time per generation call (`evaluation_generation.CallTimer`), compilation apart.
Beside the gates (issue 19): whether a sheet carries shape to its slot, as gate 3 shows it
carries colour (`evaluation_shape_transfer`).

The generated object is found by its difference from the VAE round trip of the object-free view
(`generated_objects`, whose docstring says how and why).
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import gin
import numpy as np

from signerf_jax.errors import InputError

FULL_SCALE = 1.0  # The ControlNet scale of prompt adherence, consistency and the shape gate.


@gin.configurable("default_model_evaluation")
@dataclasses.dataclass(frozen=True)
class EvaluationSettings:
  """What is evaluated and how (gin: `default_model_evaluation.<field>`).

  The diffusion knobs (steps, guidance, paste-back) are `pipeline.GenerationOptions`'; its
  ControlNet scale is replaced by each scale evaluated.

  Attributes:
    num_singles: the first eval single views used for prompt and shape adherence.
    num_sheets: at most this many eval sheets whose caption names no colour (consistency).
    controlnet_scales: the shape sweep, ascending from 0, including FULL_SCALE.
    seed: every generation's key derives from it (`evaluation_generation.evaluation_key`).
    singles_per_device, sheets_per_device: samples each device generates per call (the
      `Generator`'s views_per_device for single views and for sheets).
    difference_threshold: a channel difference from the VAE round trip of the background above
      which a masked pixel is object (`generated_objects`).
    min_component_pixels: smaller object components are dropped, smaller holes filled.
    proxy_mask_dilation, proxy_mask_feather: proxy masks as the pipeline grows them, measured
      beside the gate (`evaluation_singles`; `SelectionConfig.dilation_radius`, `feather_radius`:
      pixels at 512 pixels; the shipped model's own growth is 8, other models' 24).
    shape_transfer_sheets: the first eval sheets (any caption) of the shape-transfer measure.
    figure_singles, figure_sheets: samples shown in the figure.
  """

  num_singles: int = 128
  num_sheets: int = 64
  controlnet_scales: tuple[float, ...] = (0.0, 0.25, 0.5, 0.75, 1.0)
  seed: int = 0
  singles_per_device: int = 8
  sheets_per_device: int = 4
  difference_threshold: float = 0.1
  min_component_pixels: int = 6
  proxy_mask_dilation: float = 24.0
  proxy_mask_feather: float = 8.0
  shape_transfer_sheets: int = 64
  figure_singles: int = 4
  figure_sheets: int = 2

  def __post_init__(self):
    scales = list(self.controlnet_scales)
    checks = {
        "num_singles": self.num_singles >= 1, "num_sheets": self.num_sheets >= 1,
        # Gate 4's rise is measured from scale 0: checked here, before any generation.
        "controlnet_scales": (FULL_SCALE in scales and scales == sorted(set(scales))
                              and scales[0] == 0),
        "singles_per_device": self.singles_per_device >= 1,
        "sheets_per_device": self.sheets_per_device >= 1,
        "difference_threshold": 0 < self.difference_threshold < 1,
        "min_component_pixels": self.min_component_pixels >= 1,
        "proxy_mask_dilation": self.proxy_mask_dilation >= 0,
        "proxy_mask_feather": self.proxy_mask_feather >= 0,
        # Its "other object" sheets hold the next sample's views: two samples at least.
        "shape_transfer_sheets": self.shape_transfer_sheets >= 2,
    }
    for name, valid in checks.items():
      if not valid:
        raise InputError(f"invalid value {getattr(self, name)!r} (counts >= 1, shape-transfer "
                         f"sheets >= 2, scales ascending from 0 and including {FULL_SCALE}, "
                         "threshold in (0, 1), radii >= 0)",
                         field=f"default_model_evaluation.{name}")


@gin.configurable("default_model_gates")
@dataclasses.dataclass(frozen=True)
class QualityGates:
  """The issue's thresholds (gin: `default_model_gates.<field>`).

  Attributes:
    min_color_adherence: share of objects in the named colour.
    min_shape_iou: mean IoU at ControlNet scale 1.
    rising_tolerance: each scale's mean IoU may fall at most this much below the previous one's
      (sampling noise), and scale 1 must beat scale 0 by more than it.
    min_agreement_margin: how much more often sheet tiles (and slot against sheet) must agree
      in colour than independently generated views ("far better").
    min_proxy_shape_iou, min_control_rise: gate 4 (issue 19: the control must matter), in the
      pipeline's proxy masks: the mean IoU of the object found by its caption's hue at ControlNet
      scale 1, and how much it must rise from scale 0.
  """

  min_color_adherence: float = 0.9
  min_shape_iou: float = 0.8
  rising_tolerance: float = 0.02
  min_agreement_margin: float = 0.3
  min_proxy_shape_iou: float = 0.75
  min_control_rise: float = 0.15


def quality_gates(color_adherence: float, mean_ious: Sequence[float], scales: Sequence[float],
                  agreement: dict[str, float], gates: QualityGates) -> dict[str, dict]:
  """Pass or fail of gates 1 - 3 with their values and thresholds.

  Args:
    color_adherence: the share of objects in the named colour.
    mean_ious: mean IoU per ControlNet scale of `scales` (ascending, including FULL_SCALE).
    agreement: {"sheet", "independent", "slot_update"} colour agreement shares.
  """
  full = mean_ious[list(scales).index(FULL_SCALE)]
  steps = np.diff(mean_ious)
  rising = bool(np.all(steps >= -gates.rising_tolerance)
                and full - mean_ious[0] > gates.rising_tolerance)
  margins = {name: agreement[name] - agreement["independent"] for name in ("sheet", "slot_update")}
  return {
      "prompt_adherence": {"value": color_adherence, "threshold": gates.min_color_adherence,
                           "passed": bool(color_adherence >= gates.min_color_adherence)},
      "shape_adherence": {"iou_at_full_scale": full, "threshold": gates.min_shape_iou,
                          "rising": rising, "rising_tolerance": gates.rising_tolerance,
                          "passed": bool(full >= gates.min_shape_iou and rising)},
      "consistency": {"margins_over_independent": margins,
                      "threshold": gates.min_agreement_margin,
                      "passed": bool(min(margins.values()) >= gates.min_agreement_margin)},
  }


def control_gate(hue_ious: Sequence[float], difference_ious: Sequence[float],
                 scales: Sequence[float], gates: QualityGates) -> dict:
  """Gate 4, whether the ControlNet steers the shape inside the pipeline's proxy masks: pass or
  fail on the mean IoU per scale of `scales` (ascending, from 0, including FULL_SCALE) of the
  objects found by their caption's hue (`hue_ious`), which counts only the object; the same of
  the difference segmentation (`difference_ious`), which also counts the ground repainted around
  it, stands beside it."""
  if scales[0] != 0:
    raise InputError(f"the rise is measured from ControlNet scale 0, got scales {list(scales)}",
                     field="default_model_evaluation.controlnet_scales")
  full = list(scales).index(FULL_SCALE)
  measure = lambda ious: {"iou_at_full_scale": ious[full],
                          "rise_from_scale_0": ious[full] - ious[0]}
  by_hue = measure(hue_ious)
  return {"by_caption_hue": by_hue, "by_difference": measure(difference_ious),
          "iou_threshold": gates.min_proxy_shape_iou, "rise_threshold": gates.min_control_rise,
          "passed": bool(by_hue["iou_at_full_scale"] >= gates.min_proxy_shape_iou
                         and by_hue["rise_from_scale_0"] >= gates.min_control_rise)}
