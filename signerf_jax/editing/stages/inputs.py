"""The stages every edit starts with (paper, Sec. 3 steps 1-2): the original NeRF, the selection,
and each training view's mask and control depth rendered from the original NeRF."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import tqdm

from signerf_jax import files
from signerf_jax.clip import tokenizer as tokenizer_lib
from signerf_jax.diffusion import pipeline
from signerf_jax.editing import conditioning as conditioning_lib
from signerf_jax.editing import select as select_lib
from signerf_jax.editing.config import EditSettings, as_json, training_key
from signerf_jax.editing.project import load_arrays, save_arrays
from signerf_jax.editing.stages.context import EditContext
from signerf_jax.errors import InputError
from signerf_jax.geometry import masks as masks_lib
from signerf_jax.geometry import reference_cameras
from signerf_jax.nerf import training_run

# Dataset views are rendered and conditioned this many at a time.
VIEWS_PER_CHUNK = 8


def check_inputs(settings: EditSettings) -> list[str]:
  """Checks the edit's inputs before any stage runs, so that a mistake surfaces in a second
  rather than after the original NeRF has trained: the directories exist, the diffusion
  model's configurations parse (`pipeline.check_pipeline`; weights are checked as they load),
  the proxy mesh loads, and the model reads the prompts as written.

  Returns:
    warnings for the user, about the prompt and negative prompt (`tokenizer.prompt_problems`):
    words the model's tokenizer does not know (they would become its unknown token, the
    words it knows listed), characters it cannot encode (e.g. emoji, which a word-level
    tokenizer drops), and the end of a prompt longer than its text encoder reads.
  Raises:
    InputError naming the file and the parameter; for those prompt problems too when
    `EditConfig.strict_prompt`.
  """
  edit = settings.edit
  for value, field in ((edit.data, "EditConfig.data"),
                       (edit.original_run, "EditConfig.original_run"),
                       (edit.controlnet, "EditConfig.controlnet"),
                       (settings.evaluation.clip_model, "EvaluationConfig.clip_model")):
    if value and not Path(value).is_dir():
      raise InputError("directory not found", value, field)
  for value, field in ((settings.sheet.reference_cameras, "SheetConfig.reference_cameras"),
                       (settings.finetune.lpips_weights, "FinetuneConfig.lpips_weights")):
    if value and not Path(value).is_file():
      raise InputError("file not found", value, field)
  try:
    tokenizers = pipeline.check_pipeline(edit.model, controlnet=edit.controlnet or None,
                                         scheduler_kind=edit.scheduler_kind or None)
  except InputError as error:
    raise InputError(error.problem, error.path or edit.model,
                     error.field or "EditConfig.model") from None
  if settings.selection.kind == "proxy":
    select_lib.load_proxy(settings.selection.proxy)
  warnings = []
  for field, text in (("prompt", edit.prompt), ("negative_prompt", edit.negative_prompt)):
    for tokenizer in tokenizers:
      for problem in tokenizer_lib.prompt_problems(tokenizer, text):
        if edit.strict_prompt:
          raise InputError(problem, edit.model, f"EditConfig.{field}")
        warnings.append(f"EditConfig.{field}: {problem}")
  return list(dict.fromkeys(warnings))  # SDXL's two tokenizers may find the same.


def original_settings(context: EditContext) -> dict[str, Any]:
  """The original stage's key: the given run, or the data, training and capacity settings."""
  settings = context.settings
  if settings.edit.original_run:
    return {"original_run": str(Path(settings.edit.original_run).resolve())}
  key = {"data": context.data_options, "train": training_key(settings.training["original"]),
         "capacity": as_json(settings.capacity)}
  # Only when set: the keys of edits made before replays existed stay as they were.
  return {**key, "replay": settings.edit.replay} if settings.edit.replay else key


def train_original(context: EditContext) -> str:
  """Step 1: trains the original NeRF on the dataset (or takes `EditConfig.original_run`);
  returns the summary line."""
  if context.settings.edit.original_run:
    trained = context.nerf(0)
    return (f"using the trained NeRF {context.original_run_dir} (step {trained.step}, "
            f"{trained.seconds_trained:.0f} s trained)")
  trainer = training_run.train(context.dataset, context.original_run_dir,
                               config=context.settings.training["original"],
                               capacity_rules=context.settings.capacity,
                               data_options=context.data_options, progress=context.progress,
                               replay_progress=context.replayed_schedule(
                                   context.original_run_dir))
  return (f"{trainer.step} steps ({trainer.seconds_trained:.0f} s) on "
          f"{context.dataset.num_images} views, last batch "
          f"{trainer.last_statistics.get('psnr', float('nan')):.2f} dB: {context.original_run_dir}")


def select(context: EditContext) -> str:
  """Step 2: writes the selection (box or proxy) to selection/; returns the summary line, which
  says how many cameras see it."""
  selection = context.selection
  written = select_lib.write_selection(context.directory.path("selection"), selection)
  seeing = reference_cameras.cameras_seeing(context.views.cameras, selection.points)
  center, radius = selection.sphere()
  what = (f"box {np.round(selection.bounds, 3).tolist()}" if selection.kind == "box"
          else f"proxy {Path(selection.proxy.source).name} ({len(selection.proxy.faces)} "
               "triangles)")
  return (f"{what} around {np.round(center, 3).tolist()} (radius {radius:.3f}), in view of "
          f"{int(seeing.sum())} of {len(seeing)} cameras: {', '.join(map(str, written))}")


def view_settings(context: EditContext) -> dict[str, Any]:
  """The views stage's key: what decides the update's tiles, whose source pixels it renders
  (`tile_sources`)."""
  sheet = context.settings.sheet
  # Without a tile size the model's native one: named by the model (not read from it).
  return {"crops": sheet.crops, "crop_margin": sheet.crop_margin,
          "crop_max_upscale": sheet.crop_max_upscale,
          "tile_size": sheet.tile_size or f"native to {context.settings.edit.model}"}


def tile_sources(context: EditContext) -> np.ndarray:
  """[N, 4] boxes [x0, y0, width, height] (pixels) holding every pixel of the training views that
  the image set update's tiles are resampled from (`context.tile_boxes`, grown by the reach of
  `crops.crop_to_tiles`' antialiased bilinear kernel: a pixel, or the downscaling factor, plus a
  pixel of margin): the diffusion model sees the control depth of all of them."""
  boxes = context.tile_boxes(context.dataset.cameras).astype(np.float64)
  layout = context.layout
  reach = np.maximum(1.0, np.maximum(boxes[:, 2] / layout.tile_width,
                                     boxes[:, 3] / layout.tile_height)) + 1.0
  return np.concatenate([boxes[:, :2] - reach[:, None], boxes[:, 2:] + 2 * reach[:, None]], -1)


def condition_views(context: EditContext) -> str:
  """Renders each training view's mask and control depth (resumable: finished views are kept)
  and records which views show the selection. Each view is rendered only where the selection,
  its mask, or the control depth the update's diffusion model sees can be
  (`conditioning.pixels_to_render`)."""
  dataset, original = context.dataset, context.nerf(0)
  selection_config = context.settings.selection
  sources = tile_sources(context)
  indices = np.arange(dataset.num_images)
  finished = [index for index in indices if context.view_path(index).is_file()]
  bar = tqdm.tqdm(total=len(indices), initial=len(finished), unit="view", desc="views",
                  disable=not context.progress, dynamic_ncols=True)
  for start in range(0, len(indices), VIEWS_PER_CHUNK):
    chunk = [index for index in indices[start:start + VIEWS_PER_CHUNK]
             if not context.view_path(index).is_file()]
    if not chunk:
      continue
    conditioned = conditioning_lib.condition_views(
        original.model, original.variables, dataset.cameras, chunk, context.selection,
        selection_config, VIEWS_PER_CHUNK, only_where_selected_can_appear=True,
        context_boxes=sources)
    for position, index in enumerate(chunk):
      save_arrays(context.view_path(index), **{name: array[position] for name, array
                                               in conditioned.arrays().items()})
    bar.update(len(chunk))
  bar.close()
  mask_pixels = np.asarray([
      np.count_nonzero(load_arrays(context.view_path(index), ("mask",))["mask"])
      for index in indices])
  empty = masks_lib.views_with_empty_masks(mask_pixels[:, None, None]
                                           >= selection_config.min_mask_pixels)
  visible = np.setdiff1d(indices, empty)
  files.write_json(context.directory.path("views", "views.json"),
                   {"visible": visible, "empty": empty, "mask_pixels": mask_pixels})
  skipped = f", {len(empty)} do not see the selection and stay as they are" if len(empty) else ""
  return (f"{dataset.num_images} training views conditioned from the original NeRF, "
          f"{len(visible)} show the selection{skipped}: {context.directory.path('views')}")
