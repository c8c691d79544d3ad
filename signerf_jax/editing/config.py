"""What an edit does and how: the settings every pipeline stage reads.

An edit is fully described by these dataclasses, which gin binds at the edge
(`editing.commands.edit_settings` builds an `EditSettings` from the bindings, saved as the edit
directory's config.gin); the command-line flags of `signerf edit` are shorthand for bindings:

  EditConfig       the inputs: dataset, original run, prompt, seed, model checkpoints, the sheet
                   to use, whether to fine-tune or retrain, the optional second iteration;
  SelectionConfig  where: an axis-aligned box, or a proxy mesh (file or primitive) placed by a
                   similarity transform or stood on the ground; mask dilation and feathering;
  SheetConfig      the reference sheet: grid, tile size, full frames or crops around the selection;
  UpdateConfig     the image set update: through the sheet or view by view; views per device;
  FinetuneConfig   the NeRF update's losses (L1, optional LPIPS on rendered patches);
  EvaluationConfig the metrics and renders written at the end;
  NerfConsistencySettings  the evaluation's measurements of the edited NeRF itself (fit,
                   solidity, correspondences; `editing.stages.nerf_consistency`).
`EditSettings` holds them with the settings owned by other modules: `GenerationOptions` (the
diffusion knobs; gin scopes `first_iteration/` and `second_iteration/` so the second iteration
can stick closer to its input, as in the paper's table), `TrainConfig` (scopes `original/`,
`finetune/` and `retrain/`), `CapacityRules`, `ReferencePlacement`, `AttentionOptions` and
`ConsistencySettings`.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Annotated, Any, Literal, Mapping

from signerf_jax import validation
from signerf_jax.diffusion.attention import AttentionOptions
from signerf_jax.diffusion.pipeline import GenerationOptions
from signerf_jax.errors import InputError
from signerf_jax.geometry.reference_cameras import ReferencePlacement
from signerf_jax.metrics.consistency import ConsistencySettings, Matcher
from signerf_jax.nerf.capacity import CapacityRules
from signerf_jax.nerf.capture_choices import USUAL_VALUES, capture_default
from signerf_jax.nerf.train import TrainConfig
from signerf_jax.validation import (NonNegativeFloat, NonNegativeInt, OpenUnitInterval,
                                    PositiveFloat, PositiveInt, Range, UnitInterval, Vector3)

# The shipped model (diffusers layout), trained by the project (see default_model/). A path,
# not an import: default_model sits above the library (it trains with the editing code).
DEFAULT_MODEL_DIR = Path(__file__).resolve().parents[1] / "default_model" / "weights"
SelectionKind = Literal["box", "proxy"]
NerfUpdate = Literal["auto", "finetune", "retrain"]
Propagation = Literal["sheet", "independent", "reference_views"]
# A scheduler class replacing the checkpoint's ("" keeps it).
SchedulerOverride = Literal["", "ddim", "dpm_solver_multistep", "euler_ancestral"]  # "" first
PRIMITIVE_PREFIX = "primitive:"
# The NeRF runs of an edit, each with its own TrainConfig (gin scope of the same name).
TRAINING_RUNS = ("original", "finetune", "retrain")
# The gin scopes of the first and second iteration's GenerationOptions (`EditSettings.generation`).
GENERATION_SCOPES = ("first_iteration", "second_iteration")


@dataclasses.dataclass(frozen=True)
class EditConfig(validation.CheckedFields):
  """The inputs of an edit.

  Attributes:
    data: the dataset directory (nerfstudio, Blender or LLFF); may be left empty when
      `original_run` records it.
    downscale: integer image downscale of the dataset.
    original_run: an already trained NeRF run of that dataset ("" trains one in the edit
      directory, gin scope `original/TrainConfig`).
    prompt, negative_prompt: the text conditioning.
    seed: seeds the image set update (and names the default sheet).
    sheet: the reference sheet to propagate, as a recipe (`generation.SheetRecipe`): "3" is the
      sheet generated with seed 3, "3/1,4@7" that sheet with tiles 1 and 4 re-rolled with seed 7.
      "" means str(seed).
    model: a diffusers inpainting pipeline directory (default: the shipped model).
    controlnet: a diffusers ControlNet directory replacing (or adding) the pipeline's ("": the
      pipeline's own).
    scheduler_kind: "ddim", "dpm_solver_multistep" or "euler_ancestral" to override the
      checkpoint's scheduler class ("" keeps it; needed for e.g. PNDM checkpoints).
    nerf_update: "finetune" (from the original parameters, re-initialised optimiser, L1 + LPIPS:
      the paper's choice for edits), "retrain" (from scratch: its choice for inserted objects),
      or "auto" (retrain for proxy selections, fine-tune for box selections).
    second_iteration: run steps 4-7 once more from the edited NeRF (paper, step 8), with the
      `second_iteration/GenerationOptions` settings.
    second_sheet: the sheet recipe of the second iteration ("": str(seed)).
    strict_prompt: a prompt word the model's tokenizer does not know is an error (by default
      a warning naming the words it knows).
    replay: an earlier edit directory whose NeRF trainings this one repeats step for step: each
      training is given the progress its counterpart's schedule had at each step (its
      schedule.json), so a time-budgeted edit repeats bit for bit with the same settings (give
      its config.gin too); "" trains as the budgets say.
    diffusion_precision: "float32", or "bfloat16": the diffusion model's weights stored and its
      matmuls and convolutions computed in bfloat16 (float32 accumulation). On CPUs with bf16
      instructions (e.g. AVX512_BF16) sampling is faster, with the shipped model and SD-sized
      UNets alike; without them it is slower, and loading warns (docs/performance.md). The
      images differ by ~0.004 in mean absolute value.
  """

  data: str = ""
  downscale: PositiveInt = 1
  original_run: str = ""
  prompt: str = ""
  negative_prompt: str = ""
  seed: NonNegativeInt = 0
  sheet: str = ""
  model: str = str(DEFAULT_MODEL_DIR)
  controlnet: str = ""
  scheduler_kind: SchedulerOverride = ""
  nerf_update: NerfUpdate = "auto"
  second_iteration: bool = False
  second_sheet: str = ""
  strict_prompt: bool = False
  replay: str = ""
  diffusion_precision: Literal["float32", "bfloat16"] = "float32"

  def __post_init__(self):
    super().__post_init__()
    if not self.prompt.strip():
      raise InputError("an edit needs a prompt", field="EditConfig.prompt")

  def sheet_recipe(self, iteration: int) -> str:
    recipe = self.sheet if iteration == 1 else self.second_sheet
    return recipe or str(self.seed)


@dataclasses.dataclass(frozen=True)
class SelectionConfig(validation.CheckedFields):
  """Where to edit (paper, "Selection Modes").

  Coordinates are in the dataset's own world units (`frame="source"`, the default: e.g. the
  COLMAP frame of a capture, Blender's frame for a synthetic scene), mapped through the
  dataset's `world_from_source`, so the same numbers mean the same place whatever frame the NeRF
  normalises into; or in that normalised scene frame itself (`frame="scene"`, the one
  `signerf train` prints the source frame against).

  Attributes:
    kind: "box" (shape selection) or "proxy" (proxy selection).
    box_min, box_max: the box's corners.
    box_mask_mode: "surface" (the NeRF surface inside the box) or "silhouette" (the whole
      visible box, letting an edit grow into empty space); see `geometry.selection`.
    proxy: a mesh file (OBJ, PLY, GLB, STL, OFF) or "primitive:<name>" with name one of box,
      sphere, cylinder, capsule, cow.
    scale, rotation_degrees, translation: the similarity transform placing the proxy (x -> t +
      s R x, R from Euler angles about x, then y, then z).
    ground_position: when given, the proxy is instead stood upright on the ground with its
      footprint centred here (`geometry.mesh.place_on_ground`), scaled so its largest side is
      `ground_size` and turned by `heading_degrees` about the scene's up direction.
    mesh_up: the proxy's own up direction (the shared meshes are +y up).
    up: the up direction, in `frame` (None: the dataset cameras' mean up vector).
    frame: "scene" or "source" (see above).
    dilation_radius, feather_radius: mask growth and soft edge in pixels at 512 pixels
      (`geometry.masks`): the generated region may exceed the selection slightly. None: the
      model's own growth (`generation.recommended_mask_dilation`: 8 for the shipped model, 24
      for others), filled in where the settings are built (`commands.edit_settings`).
    min_accumulation: NeRF opacity below which a pixel counts as empty.
    min_mask_pixels: views with fewer mask pixels are not edited (reported).
  """

  kind: SelectionKind = "box"
  box_min: Vector3 | None = None
  box_max: Vector3 | None = None
  box_mask_mode: Literal["surface", "silhouette"] = "surface"
  proxy: str = ""
  scale: PositiveFloat = 1.0
  rotation_degrees: Vector3 = (0.0, 0.0, 0.0)
  translation: Vector3 = (0.0, 0.0, 0.0)
  ground_position: Vector3 | None = None
  ground_size: PositiveFloat = 0.5
  heading_degrees: float = 0.0
  mesh_up: Vector3 = (0.0, 1.0, 0.0)
  up: Vector3 | None = None
  frame: Literal["scene", "source"] = "source"
  dilation_radius: NonNegativeFloat | None = None
  feather_radius: NonNegativeFloat = 8.0
  min_accumulation: UnitInterval = 0.5
  min_mask_pixels: NonNegativeInt = 1

  def __post_init__(self):
    super().__post_init__()
    if self.kind == "box" and (self.box_min is None or self.box_max is None):
      raise InputError("a box selection needs box_min and box_max (--box)", field="box")
    if self.kind == "proxy" and not self.proxy:
      raise InputError("a proxy selection needs a mesh file or primitive (--proxy)",
                       field="proxy")


@dataclasses.dataclass(frozen=True)
class SheetConfig(validation.CheckedFields):
  """The reference sheet (paper, "Reference Sheet"; `editing.sheet`).

  Attributes:
    rows, columns, slot_row, slot_column: the grid and its empty slot (2 x 3 holds the paper's
      five reference views).
    tile_size: tile side in pixels; None = the model's native resolution (64 for the shipped
      model, 512 for SD 1.5, 1024 for SDXL).
    reference_cameras: "" places them automatically; otherwise a Blender-style JSON file
      (`camera_angle_x`, `frames[].transform_matrix`, scene frame) with one camera per tile.
    crops: tiles of dataset views are crops around the selection (`editing.crops`), pasted back
      through the mask, instead of whole downscaled frames (False). On by default: the
      selection gets more of its tile's pixels (often many times more), and edits measure
      better end to end, in the demo and on a real scene (docs/results.md).
    crop_margin, crop_max_upscale: see `crops.selection_crop_boxes`.
  """

  rows: PositiveInt = 2
  columns: PositiveInt = 3
  slot_row: int = -1
  slot_column: int = -1
  tile_size: PositiveInt | None = None
  reference_cameras: str = ""
  crops: bool = True
  crop_margin: NonNegativeFloat = 0.15
  crop_max_upscale: PositiveFloat = 2.0


@dataclasses.dataclass(frozen=True)
class PreviewConfig(validation.CheckedFields):
  """The candidate sheets `signerf preview` shows side by side.

  Attributes:
    seeds: one fresh sheet per seed.
    recipes: further sheet recipes, e.g. re-rolls "2/1,4@7" of tiles of a candidate.
  """

  seeds: tuple[NonNegativeInt, ...] = (0, 1, 2, 3)
  recipes: tuple[str, ...] = ()


@dataclasses.dataclass(frozen=True)
class UpdateConfig(validation.CheckedFields):
  """The image set update (`editing.update`).

  Attributes:
    views_per_device: views each device inpaints per batch; the batch is this times the number
      of devices (the last batch is padded). A fixed per-device size keeps every device's
      program the same whatever the device count.
    propagation: "sheet" inpaints each view in the empty slot of the reference sheet (the
      paper's image set update); for comparisons, "independent" inpaints each view on its own,
      with no sheet (the paper's baseline for 3D consistency), and "reference_views" updates no
      view: the NeRF learns the sheet's tiles at the reference cameras alone (what the image
      set update adds).
  """

  views_per_device: PositiveInt = 4
  propagation: Propagation = "sheet"


@dataclasses.dataclass(frozen=True)
class FinetuneConfig(validation.CheckedFields):
  """Losses of the NeRF update (`editing.finetune`); steps and learning rates are
  `finetune/TrainConfig` and `retrain/TrainConfig`.

  Attributes:
    lpips_weights: a safetensors file of VGG-LPIPS weights (`metrics.lpips`); "" = no LPIPS.
    lpips_weight: the LPIPS term's weight (the paper applies LPIPS when fine-tuning edits).
    patch_size: side of the square patches rendered for LPIPS (at least 16).
    edit_region: the updated NeRF is rendered only inside the selection's box (grown by
      `region_margin`), over the frozen original NeRF everywhere else (`nerf.model`'s edit
      regions): nothing outside the box can change, however the edited views disagree. False
      updates the whole scene, as the paper does.
    region_margin: added to every side of the selection's box, as a fraction of its largest
      side (the generated object may exceed the selection a little, as the masks may).
    region_view_dependence: a retrained edit region colours by view direction, as the
      original NeRF does; False makes it diffuse (`NerfModel.region_view_dependence`). A
      fine-tune starts from the original's field and keeps its view dependence.
  """

  lpips_weights: str = ""
  lpips_weight: NonNegativeFloat = 0.1
  patch_size: Annotated[int, Range(16)] = 32
  edit_region: bool = True
  region_margin: NonNegativeFloat = 0.25
  region_view_dependence: bool = True


@dataclasses.dataclass(frozen=True)
class EvaluationConfig(validation.CheckedFields):
  """What `signerf eval --edit` measures and writes.

  Attributes:
    clip_model: a transformers CLIP checkpoint (`clip.similarity`); "" skips CLIP.
    source_caption: CLIP's caption of the unedited scene.
    independent_views: how many edited views get an independent per-view edit for the
      consistency comparison (0 skips it: a diffusion sampling a view, which the demo and the
      benchmarks spend and an everyday edit need not).
    video_frames: frames of the before/after orbit video (0: no video; each frame is a full
      render of the original NeRF, the edited one re-rendered only where its edit region shows).
    video_fps: its frame rate.
  """

  clip_model: str = ""
  source_caption: str = "a photo of a scene"
  independent_views: NonNegativeInt = 0
  video_frames: NonNegativeInt = 0
  video_fps: PositiveInt = 12


@dataclasses.dataclass(frozen=True)
class NerfConsistencySettings(validation.CheckedFields):
  """How the edited NeRF is measured (`editing.stages.nerf_consistency`).

  Attributes:
    enabled: measure it in the evaluate stage (it renders every edited training view, and the
      held-out views at `correspondence_size`).
    support_clearance: share of the selection box's height, from its bottom along the up axis,
      left out of the opacity.
    opacity_threshold: opacity above which a pixel is the object.
    correspondence_size: the longer side (px) of the renders matched for correspondences.
    correspondence_views: held-out cameras rendered for correspondences (evenly spaced).
    correspondence_matcher: how those renders are matched (`metrics.consistency`; the rest of
      `ConsistencySettings` applies): "tracked" by default, since renders of a NeRF trained on
      small views are soft, and SIFT finds about one verified match per pair in them (demo).
    num_resamples, confidence, seed: the bootstrap.
  """

  enabled: bool = False
  support_clearance: UnitInterval = 0.05
  opacity_threshold: OpenUnitInterval = 0.5
  correspondence_size: PositiveInt = 256
  correspondence_views: PositiveInt = 12
  correspondence_matcher: Matcher = "tracked"
  num_resamples: PositiveInt = 2000
  confidence: OpenUnitInterval = 0.95
  seed: NonNegativeInt = 0

  def bootstrap(self) -> dict[str, Any]:
    return {"num_resamples": self.num_resamples, "confidence": self.confidence,
            "seed": self.seed}


@dataclasses.dataclass(frozen=True)
class EditSettings:
  """Everything an edit reads, built once where gin is parsed and passed to every stage.

  Attributes:
    edit, selection, sheet, preview, update, finetune, evaluation: the configs above.
    generation: the diffusion settings of the first and the second iteration.
    training: TrainConfig of each run in TRAINING_RUNS.
    capacity: the rules sizing a new NeRF (the original one, and a retrained one).
    placement: how the reference cameras are placed around the selection.
    attention: how the diffusion models evaluate attention (speed and memory, not results).
    consistency: the consistency measurement of the evaluation.
    nerf_consistency: the evaluation's measurements of the edited NeRF itself.
    gin_config: the gin bindings these settings came from (config.gin, provenance).
  """

  edit: EditConfig
  selection: SelectionConfig
  sheet: SheetConfig = SheetConfig()
  preview: PreviewConfig = PreviewConfig()
  update: UpdateConfig = UpdateConfig()
  finetune: FinetuneConfig = FinetuneConfig()
  evaluation: EvaluationConfig = EvaluationConfig()
  generation: tuple[GenerationOptions, GenerationOptions] = (GenerationOptions(),
                                                             GenerationOptions())
  training: Mapping[str, TrainConfig] = dataclasses.field(
      default_factory=lambda: {run: TrainConfig() for run in TRAINING_RUNS})
  capacity: CapacityRules = CapacityRules()
  placement: ReferencePlacement = ReferencePlacement()
  attention: AttentionOptions = AttentionOptions()
  consistency: ConsistencySettings = ConsistencySettings()
  nerf_consistency: NerfConsistencySettings = NerfConsistencySettings()
  gin_config: str = ""

  def __post_init__(self):
    if set(self.training) != set(TRAINING_RUNS):
      raise InputError(f"needs a TrainConfig for each of {TRAINING_RUNS}, got "
                       f"{sorted(self.training)}", field="EditSettings.training")
    if self.selection.dilation_radius is None:
      raise InputError("is None: set it, or build the settings with commands.edit_settings, "
                       "which takes the model's (generation.recommended_mask_dilation)",
                       field="SelectionConfig.dilation_radius")

  def generation_options(self, iteration: int) -> GenerationOptions:
    return self.generation[0 if iteration == 1 else 1]


def as_json(config: Any) -> dict[str, Any]:
  """A settings dataclass as a JSON-friendly dict (for provenance and stage keys)."""
  return {field.name: _jsonable(getattr(config, field.name))
          for field in dataclasses.fields(config)}


# TrainConfig fields added after edits were first keyed stay out of a training's key at their
# defaults, the settings left to the capture are keyed as they were: earlier NeRFs stay.
LATER_TRAINING_FIELDS = ("keypoint_depth_weight", "keypoint_rays", "photo_consistency_weight",
                         "photo_consistency_neighbours", "photo_consistency_truncation",
                         "visual_hull")


def training_key(config: TrainConfig) -> dict[str, Any]:
  """A NeRF training's settings for its stage key (`as_json`, with the fields above)."""
  key = {name: value for name, value in as_json(config).items()
         if not (name in LATER_TRAINING_FIELDS and value == getattr(TrainConfig(), name))}
  return key | {name: capture_default(config, name) for name in USUAL_VALUES}


def _jsonable(value):
  if isinstance(value, tuple):
    return [_jsonable(item) for item in value]
  if isinstance(value, Path):
    return str(value)
  return value
