"""The default model's quality gates (issue 5), measured on the held-out procedural data.

Every generation inpaints the object-free view (`background_rgb`) under the object's "box" mask
(`batches.box_masks`: its silhouette's bounding box plus a margin, so only position and extent are
given and the shape has to come from the control depth), with the stored control depth and the
sample's caption, starting from noise:

1. Prompt adherence: single views whose caption names a colour, at ControlNet scale 1; a view
   passes when the dominant colour (`metrics.colors.dominant_color`) of its generated object's pixels
   is the caption's colour (`editing.evaluation.prompt_color_adherence`). No object: a miss.
   Its ceiling (`vae_ceiling`): the share of the same views whose true render keeps its colour
   through the VAE round trip (what a perfect denoiser can reach through this VAE).
2. Shape adherence: the same single views at every ControlNet scale, each view with one key at
   all scales (so only the scale differs); the IoU of the generated object's silhouette with the
   true one. The gate: IoU at scale 1 >= the threshold and rising with the scale.
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
   independent views' by at least a margin.
4. Time per generation call (`CallTimer`), compilation apart.

Segmenting the generated object. Inside the inpainting mask (where the model regenerated
everything, object and ground), a pixel belongs to the object when its colour differs in some
channel by more than `difference_threshold` from the *VAE round trip* of the object-free view
(`vae_round_trip`: encode, take the posterior mode, decode). Comparing with the round trip rather
than the exact background cancels what the VAE alone loses (blurred ground textures, slight
colour shifts), which every generated pixel goes through too. Then connected components (4-
connected) smaller than `min_component_pixels` are dropped (isolated specks of regenerated
texture) and holes smaller than that are filled (object pixels that happen to match the ground).
Only area, not morphological opening, is used: opening also erases the thin parts (legs,
handles) of the small objects of 64-pixel views, which costs about 5 IoU points on the true
renders, against under 1 for this. Applied to the VAE round trip of the true renders, the
segmentation gives the shape IoU a perfect generator would reach (`segmentation_ceiling_iou`).

Beside the gate, shape adherence is also reported (not gates) with the pipeline's own proxy masks
(`with_proxy_masks`: the silhouette dilated and feathered as `SelectionConfig` does for a proxy
by default, about 3 pixels at 64; the paper inpaints the visible proxy, "further dilated", while
the gate's boxes leave the whole shape to the depth), with where the IoU is lost (pooled
precision and recall, and the share of masked ground pixels off by more than the threshold), and
with the object found by its caption's hue (`segment_by_hue`, views whose caption names a
chromatic colour): the masked pixels whose hue is nearest that colour's
(`metrics.colors.pixel_hue_colors`), cleaned the same way. Repainted ground and background rarely
take the object's hue, so this measures the object's own silhouette where the difference
segmentation also counts a hazy repaint of the box as object.
"""

from __future__ import annotations

import dataclasses
import itertools
import time
from typing import Callable, Sequence

import cv2
import gin
import jax
import jax.numpy as jnp
import numpy as np

from signerf_jax import parallel
from signerf_jax.default_model import batches
from signerf_jax.default_model import captions as captions_lib
from signerf_jax.default_model import samples
from signerf_jax.diffusion import pipeline as pipeline_lib
from signerf_jax.diffusion import sampler
from signerf_jax.editing import evaluation as editing_evaluation
from signerf_jax.editing import sheet as sheet_lib
from signerf_jax.editing.generation import Generator, SheetInputs
from signerf_jax.errors import InputError
from signerf_jax.geometry import masks as masks_lib
from signerf_jax.metrics import colors

FULL_SCALE = 1.0  # The ControlNet scale of prompt adherence, consistency and the shape gate.
KEY_PURPOSES = ("single", "sheet", "independent", "slot")


@gin.configurable("default_model_evaluation")
@dataclasses.dataclass(frozen=True)
class EvaluationSettings:
  """What is evaluated and how (gin: `default_model_evaluation.<field>`).

  The diffusion knobs (steps, guidance, paste-back) are `pipeline.GenerationOptions`'; its
  ControlNet scale is replaced by each scale evaluated.

  Attributes:
    num_singles: the first eval single views used for prompt and shape adherence.
    num_sheets: at most this many eval sheets whose caption names no colour (consistency).
    controlnet_scales: the shape sweep, ascending, including FULL_SCALE.
    seed: every generation's key derives from it (`evaluation_key`).
    singles_per_device, sheets_per_device: samples each device generates per call (the
      `Generator`'s views_per_device for single views and for sheets).
    difference_threshold: a channel difference from the VAE round trip of the background above
      which a masked pixel is object (module docstring).
    min_component_pixels: smaller object components are dropped, smaller holes filled.
    proxy_mask_dilation, proxy_mask_feather: the pipeline's proxy masks, measured beside the
      gate (`SelectionConfig.dilation_radius`, `feather_radius`: pixels at 512 pixels).
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
  figure_singles: int = 4
  figure_sheets: int = 2

  def __post_init__(self):
    scales = list(self.controlnet_scales)
    checks = {
        "num_singles": self.num_singles >= 1, "num_sheets": self.num_sheets >= 1,
        "controlnet_scales": scales == sorted(set(scales)) and FULL_SCALE in scales,
        "singles_per_device": self.singles_per_device >= 1,
        "sheets_per_device": self.sheets_per_device >= 1,
        "difference_threshold": 0 < self.difference_threshold < 1,
        "min_component_pixels": self.min_component_pixels >= 1,
        "proxy_mask_dilation": self.proxy_mask_dilation >= 0,
        "proxy_mask_feather": self.proxy_mask_feather >= 0,
    }
    for name, valid in checks.items():
      if not valid:
        raise InputError(f"invalid value {getattr(self, name)!r} (counts >= 1, scales ascending "
                         f"and including {FULL_SCALE}, threshold in (0, 1), radii >= 0)",
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
  """

  min_color_adherence: float = 0.9
  min_shape_iou: float = 0.8
  rising_tolerance: float = 0.02
  min_agreement_margin: float = 0.3


# ------------------------------------------------------------------------------------------------
# Metrics (pure, numpy).


def _keep_components(binary: np.ndarray, min_pixels: int) -> np.ndarray:
  """[H, W] bool: the 4-connected components of `binary` with at least `min_pixels` pixels."""
  _, labels, stats, _ = cv2.connectedComponentsWithStats(binary.astype(np.uint8), connectivity=4)
  keep = stats[:, cv2.CC_STAT_AREA] >= min_pixels
  keep[0] = False  # Label 0 is the zero pixels.
  return keep[labels]


def segment_objects(generated: np.ndarray, reference: np.ndarray, masks: np.ndarray,
                    difference_threshold: float, min_component_pixels: int) -> np.ndarray:
  """The generated objects (module docstring, "Segmenting the generated object").

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
  return _without_specks(changed, min_component_pixels) & inside


def _without_specks(views: np.ndarray, min_pixels: int) -> np.ndarray:
  """[N, H, W] bool views with components smaller than `min_pixels` dropped and holes smaller
  than that filled."""
  cleaned = []
  for view in views:
    view = _keep_components(view, min_pixels)
    cleaned.append(view | (~view & ~_keep_components(~view, min_pixels)))
  return np.stack(cleaned)


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
  return _without_specks(chromatic & (nearest == named[:, None, None]) & inside,
                         min_component_pixels) & inside


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


def evaluation_key(seed: int, purpose: str, sample_index: int, view_index: int = 0) -> np.ndarray:
  """[2] uint32 key data of one generation: a `KEY_PURPOSES` entry, sample and view."""
  key = jax.random.PRNGKey(seed)
  for number in (KEY_PURPOSES.index(purpose), sample_index, view_index):
    key = jax.random.fold_in(key, number)
  return np.asarray(key)


# ------------------------------------------------------------------------------------------------
# Inputs and generation.


@dataclasses.dataclass(frozen=True)
class ViewInputs:
  """Per-view inputs of eval samples, [S, V, ...] (float32 unless said).

  Attributes:
    background: [S, V, H, W, 3] the object-free views in [0, 1] (what is inpainted).
    masks: [S, V, H, W] the box inpainting masks.
    controls: [S, V, H, W] normalised control depth of the views with the object.
    silhouettes: [S, V, H, W] bool, the true object silhouettes.
    truth: [S, V, H, W, 3] the true renders with the object in [0, 1].
    view_kinds: [S, V] indices into `samples.VIEW_KINDS`.
    captions: [S] captions.
  """

  background: np.ndarray
  masks: np.ndarray
  controls: np.ndarray
  silhouettes: np.ndarray
  truth: np.ndarray
  view_kinds: np.ndarray
  captions: list[str]

  @classmethod
  def from_arrays(cls, arrays: dict[str, np.ndarray], indices) -> "ViewInputs":
    """The samples `indices` of a loaded split's sheets or singles (`training_data.load_split`
    with keep=None)."""
    chosen = {name: arrays[name][np.asarray(indices, np.int64)]
              for name in ("rgb", "background_rgb", "depth", "control_near_far", "silhouette",
                           "boxes", "view_kinds", "caption")}
    height, width = chosen["silhouette"].shape[-2:]
    return cls(background=chosen["background_rgb"].astype(np.float32) / 255.0,
               masks=batches.box_masks(chosen["boxes"], height, width),
               controls=np.asarray(batches.control(chosen)),
               silhouettes=chosen["silhouette"] > 0,
               truth=chosen["rgb"].astype(np.float32) / 255.0,
               view_kinds=chosen["view_kinds"],
               captions=[str(text) for text in chosen["caption"]])


def select_samples(singles: dict[str, np.ndarray], sheets: dict[str, np.ndarray],
                   settings: EvaluationSettings) -> tuple[np.ndarray, np.ndarray]:
  """(indices of the single views, indices of the sheets whose caption names no colour)."""
  available = len(singles["caption"])
  if settings.num_singles > available:
    raise InputError(f"asked for {settings.num_singles} single views, the split has {available}",
                     field="default_model_evaluation.num_singles")
  uncoloured = np.flatnonzero(~np.asarray(sheets["names_color"], bool))
  if not len(uncoloured):
    raise InputError("no sheet caption leaves the colour out: consistency cannot be measured",
                     field="names_color")
  return np.arange(settings.num_singles), uncoloured[:settings.num_sheets]


@jax.jit
def vae_round_trip(models: sampler.DiffusionModels, images: jax.Array) -> jax.Array:
  """[N, H, W, 3] images in [0, 1] encoded (posterior mode) and decoded, one at a time."""
  vae = models.vae

  def one(image):
    posterior = vae.apply({"params": models.vae_params}, image[None] * 2.0 - 1.0,
                          method=vae.encode)
    return vae.apply({"params": models.vae_params}, posterior.mode(), method=vae.decode)[0]

  return jnp.clip(jax.lax.map(one, images) * 0.5 + 0.5, 0.0, 1.0)


def round_trip(generator: Generator, images: np.ndarray) -> np.ndarray:
  """`vae_round_trip` of [..., H, W, 3] images, keeping the leading axes."""
  flat = np.asarray(images, np.float32).reshape((-1,) + images.shape[-3:])
  return np.asarray(vae_round_trip(generator.pipeline.models, flat)).reshape(images.shape)


class CallTimer:
  """Wall time of generation calls per task, telling apart the first call of each compiled
  program (an input shape with a batch size: `Generator` calls with equal ones share one
  compiled sampler), which includes the compilation."""

  def __init__(self):
    self.calls: dict[str, list[tuple[float, int, bool]]] = {}
    self._programs: set[tuple] = set()

  def time(self, task: str, input_shape: tuple, batch_size: int, function: Callable, *args):
    """Runs `function(*args)`, a call generating a batch of `batch_size` samples of
    `input_shape` (a partial batch is padded to it), and records its wall time."""
    start = time.perf_counter()
    result = function(*args)
    seconds = time.perf_counter() - start
    program = (tuple(input_shape), batch_size)
    self.calls.setdefault(task, []).append((seconds, batch_size, program not in self._programs))
    self._programs.add(program)
    return result

  def summary(self) -> dict[str, dict]:
    """Per task: calls, batch size, the median time of the calls that compiled nothing and that
    per sample of the batch, and the program's first call with the compilation in it
    (compile_seconds = first call - steady median; None without steady calls)."""
    result = {}
    for task, calls in self.calls.items():
      steady = [seconds for seconds, _, first in calls if not first]
      batch_size = calls[0][1]
      median = float(np.median(steady)) if steady else None
      entry = {"calls": len(calls), "batch_size": batch_size, "steady_call_seconds": median,
               "seconds_per_sample": None if median is None else median / batch_size}
      first = [seconds for seconds, _, is_first in calls if is_first]
      if first:
        entry["first_call_seconds"] = first[0]
        entry["compile_seconds"] = None if median is None else first[0] - median
      result[task] = entry
    return result


def generate_with_captions(generator: Generator, captions: Sequence[str], image, mask, control,
                           keys, timer: CallTimer, task: str) -> np.ndarray:
  """Inpaints N samples, each with its own caption, in calls of `generator.batch_size`.

  Args:
    image: [N, H, W, 3]; mask, control: [N, H, W] or [N, H, W, 1]; keys: [N, 2] key data.
  Returns:
    [N, H, W, 3] float32 in [0, 1].
  """
  with_channels = lambda array: np.asarray(array, np.float32).reshape(np.shape(image)[:3] + (-1,))
  image, mask, control = with_channels(image), with_channels(mask), with_channels(control)
  outputs = []
  for start in range(0, len(captions), generator.batch_size):
    part = slice(start, start + generator.batch_size)
    texts = list(captions[part])
    count = len(texts)
    # Always batch_size prompt rows (the last repeated): one prompt shape, one compiled program.
    texts += texts[-1:] * (generator.batch_size - count)
    prompt = parallel.replicate(pipeline_lib.encode_prompts(generator.pipeline, texts),
                                generator.mesh)
    outputs.append(timer.time(task, image.shape[1:], generator.batch_size,
                              dataclasses.replace(generator, prompt=prompt),
                              image[part], mask[part], control[part], keys[part]))
  return np.concatenate(outputs)


def with_scale(generator: Generator, scale: float) -> Generator:
  """The generator at another ControlNet scale (traced: no recompilation)."""
  return dataclasses.replace(generator, options=dataclasses.replace(
      generator.options, controlnet_conditioning_scale=float(scale)))


# ------------------------------------------------------------------------------------------------
# The measures.


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
  background, masks, controls, silhouettes, truth = (
      array[:, 0] for array in (views.background, views.masks, views.controls, views.silhouettes,
                                views.truth))
  keys = np.stack([evaluation_key(settings.seed, "single", index)
                   for index in range(len(views.captions))])
  reference = round_trip(generator, background)

  def sweep(inpainting_masks: np.ndarray) -> tuple[list, list, dict]:
    """Generations and found objects per scale under `inpainting_masks`, and their shape
    measures."""
    generated, objects = [], []
    for scale in settings.controlnet_scales:
      generated.append(generate_with_captions(
          with_scale(generator, scale), views.captions, background, inpainting_masks, controls,
          keys, timer, "single_view"))
      objects.append(segment_objects(generated[-1], reference, inpainting_masks,
                                     settings.difference_threshold,
                                     settings.min_component_pixels))
    ious = [silhouette_iou(found, silhouettes) for found in objects]
    precision_recall = [pooled_precision_recall(found, silhouettes) for found in objects]
    return generated, objects, {
        "mean_iou": [float(np.mean(values)) for values in ious],
        "median_iou": [float(np.median(values)) for values in ious],
        # Where the IoU is lost: pixels taken beside the object or object pixels missed, and
        # how much of the repainted ground differs from the original.
        "pooled_precision": [precision for precision, _ in precision_recall],
        "pooled_recall": [recall for _, recall in precision_recall],
        "changed_ground_share": [
            changed_ground_share(images, reference, inpainting_masks, silhouettes,
                                 settings.difference_threshold) for images in generated],
        "no_object_found": [int(np.sum(~found.any((1, 2)))) for found in objects],
        "per_view": ious}

  generated, objects, shape = sweep(masks)
  truth_round_trip = round_trip(generator, truth)
  ceiling = lambda inpainting_masks: float(np.mean(silhouette_iou(segment_objects(
      truth_round_trip, reference, inpainting_masks, settings.difference_threshold,
      settings.min_component_pixels), silhouettes)))
  # Not a gate: the same with the pipeline's own proxy-placement masks (the visible proxy,
  # dilated and feathered as `SelectionConfig` does by default), as the paper inpaints.
  proxy_masks = np.asarray(masks_lib.dilate_and_feather(
      silhouettes, radius=settings.proxy_mask_dilation, feather=settings.proxy_mask_feather))
  _, _, with_proxy_masks = sweep(proxy_masks)
  with_proxy_masks.pop("per_view")
  with_proxy_masks["segmentation_ceiling_iou"] = ceiling(proxy_masks)
  # The same objects found by their caption's hue, where it names one (not a gate).
  named_colors = [captions_lib.parse_caption(caption).color for caption in views.captions]
  hue_views = [index for index, color in enumerate(named_colors)
               if color in colors.CHROMATIC_COLORS]

  def hue_iou(images: np.ndarray) -> float:
    if not hue_views:
      return float("nan")
    found = segment_by_hue(images[hue_views], masks[hue_views],
                           [named_colors[index] for index in hue_views],
                           settings.min_component_pixels)
    return float(np.mean(silhouette_iou(found, silhouettes[hue_views])))

  full = list(settings.controlnet_scales).index(FULL_SCALE)
  by_color: dict[str, list[bool]] = {}
  kept_by_vae = []
  missing = 0
  for index, caption in enumerate(views.captions):
    adherence = editing_evaluation.prompt_color_adherence(
        caption, generated[full][index][None], objects[full][index][None])
    named = captions_lib.parse_caption(caption).color
    if named is not None:
      missing += adherence is None
      by_color.setdefault(named, []).append(adherence is not None and adherence["share"] == 1.0)
      kept = editing_evaluation.prompt_color_adherence(
          caption, truth_round_trip[index][None], silhouettes[index][None])
      kept_by_vae.append(kept is not None and kept["share"] == 1.0)
  hits = [hit for values in by_color.values() for hit in values]
  kinds = {kind: views.view_kinds[:, 0] == code for code, kind in enumerate(samples.VIEW_KINDS)}
  return {
      "prompt_adherence": {
          "samples": len(hits), "controlnet_scale": FULL_SCALE,
          "share": float(np.mean(hits)) if hits else float("nan"),
          "per_color": {color: float(np.mean(values)) for color, values in sorted(by_color.items())},
          "no_object_found": int(missing),
          "vae_ceiling": float(np.mean(kept_by_vae)) if kept_by_vae else float("nan")},
      "shape_adherence": {
          "samples": len(views.captions), "controlnet_scales": list(settings.controlnet_scales),
          **{name: values for name, values in shape.items() if name != "per_view"},
          "mean_iou_by_view_kind": {kind: [float(np.mean(values[chosen]))
                                           for values in shape["per_view"]]
                                    for kind, chosen in kinds.items() if chosen.any()},
          "segmentation_ceiling_iou": ceiling(masks),
          "with_proxy_masks": {"dilation": settings.proxy_mask_dilation,
                               "feather": settings.proxy_mask_feather, **with_proxy_masks},
          "by_caption_hue": {"samples": len(hue_views),
                             "mean_iou": [hue_iou(images) for images in generated],
                             "segmentation_ceiling_iou": hue_iou(truth_round_trip)}},
  }, {"generated": np.stack(generated), "objects": np.stack(objects)}


def evaluate_consistency(generator: Generator, single_generator: Generator, sheets: ViewInputs,
                         layout: sheet_lib.SheetLayout, settings: EvaluationSettings,
                         timer: CallTimer) -> tuple[dict, dict]:
  """Colour agreement of sheet tiles, independent views and slot updates (module docstring).

  Args:
    generator: the sheets' and slot updates' generator (`settings.sheets_per_device`).
    single_generator: the independent views' generator.
    sheets: sheet samples ([S, M + 1, ...]: the M tile views, then the slot view).
    layout: the sheets' layout (M tiles of the views' size).
  Returns:
    (the measures, {"sheet_inputs": [S] SheetInputs, "sheets": [S, SH, SW, 3] generated
     sheets, "slot_updates": [S, SH, SW, 3], "independent": [S, M, H, W, 3]}).
  """
  count, tiles = len(sheets.captions), layout.num_tiles
  generator, single_generator = (with_scale(one, FULL_SCALE)
                                 for one in (generator, single_generator))
  reference = round_trip(generator, sheets.background)
  keys = lambda purpose, views: np.stack([evaluation_key(settings.seed, purpose, index, view)
                                          for index in range(count) for view in views])
  flat = lambda array: array.reshape((-1,) + array.shape[2:])

  def colors(images: np.ndarray, views: Sequence[int]):
    """(names [S][V], mean colours [S, V, 3]) of generated views [S, V, H, W, 3]."""
    views = list(views)
    objects = segment_objects(flat(images), flat(reference[:, views]),
                              flat(sheets.masks[:, views]), settings.difference_threshold,
                              settings.min_component_pixels)
    names, means = object_colors(flat(images), objects)
    return ([names[index * len(views):(index + 1) * len(views)] for index in range(count)],
            means.reshape(count, len(views), 3))

  inputs = [SheetInputs.from_tiles(sheets.background[index, :tiles],
                                   sheets.controls[index, :tiles], sheets.masks[index, :tiles],
                                   layout) for index in range(count)]
  stacked = lambda name: np.stack([getattr(one, name) for one in inputs])
  generated = generate_with_captions(generator, sheets.captions, stacked("rgb"), stacked("mask"),
                                     stacked("control"), keys("sheet", [0]), timer, "sheet")
  generated_tiles = np.stack([sheet_lib.disassemble(sheet, layout)[0] for sheet in generated])

  # The slot view (stored last) in the slot of its fixed generated sheet.
  in_slot = [sheet_lib.slot_update_inputs(
      sheet, one.control, sheets.background[index, tiles][None],
      sheets.controls[index, tiles][None, ..., None], sheets.masks[index, tiles][None, ..., None],
      layout=layout) for index, (sheet, one) in enumerate(zip(generated, inputs))]
  image, control, mask = (np.concatenate([part[position] for part in in_slot])
                          for position in range(3))
  updated = generate_with_captions(generator, sheets.captions, image, mask, control,
                                   keys("slot", [0]), timer, "slot_update")
  slots = np.stack([sheet_lib.disassemble(sheet, layout)[1] for sheet in updated])

  independent = generate_with_captions(
      single_generator, [text for text in sheets.captions for _ in range(tiles)],
      flat(sheets.background[:, :tiles]), flat(sheets.masks[:, :tiles]),
      flat(sheets.controls[:, :tiles]), keys("independent", range(tiles)), timer,
      "single_view").reshape(generated_tiles.shape)

  names, means = {}, {}
  names["sheet"], means["sheet"] = colors(generated_tiles, range(tiles))
  names["independent"], means["independent"] = colors(independent, range(tiles))
  names["slot_update"], means["slot_update"] = colors(slots[:, None], [tiles])
  against = lambda name, index: names["sheet"][index] if name == "slot_update" else None
  against_means = lambda name, index: means["sheet"][index] if name == "slot_update" else None
  return {
      "sheets": count, "controlnet_scale": FULL_SCALE,
      "slot_crop_views": int(np.sum(sheets.view_kinds[:, tiles]
                                    == samples.VIEW_KINDS.index("crop"))),
      "agreement": {name: float(np.mean([color_agreement(names[name][index],
                                                         against(name, index))
                                         for index in range(count)])) for name in names},
      "mean_rgb_distance": {name: float(np.nanmean([mean_color_distance(
          means[name][index], against_means(name, index)) for index in range(count)]))
                            for name in means},
      "no_object_found": {name: int(sum(color is None for row in names[name] for color in row))
                          for name in names},
  }, {"sheet_inputs": inputs, "sheets": generated, "slot_updates": updated,
      "independent": independent}
