"""The SIGNeRF pipeline (paper, Sec. 3 "Scene Integrated Generation"), stage by stage.

  original     1. train the original NeRF on the dataset's training views (or use a given run)
  select       2. the box or placed proxy, checked against the dataset
  views        the mask and control depth of every training view, from the original NeRF
  reference    3-4. place the reference cameras; render their tiles (colour, mask, control)
  preview      candidate sheets for several seeds (and re-rolls) side by side in one PNG
  sheet        5. the chosen sheet (a recipe: seed and re-rolled tiles)
  update       6. the image set update (vmapped, sharded, resumable per view)
  dataset      the edited dataset in nerfstudio format, with provenance
  finetune     7. fine-tune the original NeRF on it, or retrain from scratch
  *_2          8. optionally: reference (rendered by the edited NeRF), sheet, update, dataset
               and finetune once more, with `second_iteration/GenerationOptions`
  evaluate     background preservation, consistency, CLIP, adherence, renders, video, timings

Every stage is a function of an `EditRun` (the directory, the gin-bound settings, and what the
stages load, cached) returning a one-line summary that names its files. A stage's *key* is the
settings it reads plus the keys of the stages it builds on; `run_edit` skips a stage whose
recorded key is current, and redoes it (clearing its folder) otherwise, so changing, say, the
sheet recipe redoes the sheet and everything after it while the NeRF and the renders stay.
"""

from __future__ import annotations

import dataclasses
import functools
import shutil
import time
from pathlib import Path
from typing import Any, Callable

import gin
import numpy as np

from signerf_jax import camera as camera_lib
from signerf_jax import configs, files
from signerf_jax.data import load_dataset
from signerf_jax.data.dataset import Dataset
from signerf_jax.diffusion import pipeline as pipeline_lib
from signerf_jax.editing import conditioning as conditioning_lib
from signerf_jax.editing import edited_dataset, evaluation, figures, finetune, generation
from signerf_jax.editing import select as select_lib
from signerf_jax.editing import sheet as sheet_lib
from signerf_jax.editing import update as update_lib
from signerf_jax.editing.config import (EditConfig, EvaluationConfig, FinetuneConfig,
                                        PreviewConfig, SelectionConfig, SheetConfig,
                                        UpdateConfig, as_json)
from signerf_jax.editing.project import (EditDirectory, canonical_json, directory_fingerprint,
                                         frame_name, load_arrays, save_arrays)
from signerf_jax.clip import similarity as clip_similarity
from signerf_jax.errors import InputError
from signerf_jax.geometry import masks as masks_lib
from signerf_jax.geometry import reference_cameras
from signerf_jax.metrics import background
from signerf_jax.nerf import checkpoint, evaluate, render, train

STAGE_KEY_FILE = ".stage_key.json"
# Dataset views are rendered and conditioned this many at a time.
VIEWS_PER_CHUNK = 8
BEFORE_AFTER_VIEWS = 4


def _scoped(scope: str, factory: Callable[[], Any]) -> Any:
  with gin.config_scope(scope):
    return factory()


class EditRun:
  """One edit: its directory, settings (read from gin when created) and cached inputs."""

  def __init__(self, directory, progress: bool = True):
    self.directory = EditDirectory(directory)
    self.progress = progress
    self.config = EditConfig()
    self.selection_config = SelectionConfig()
    self.sheet_config = SheetConfig()
    self.preview_config = PreviewConfig()
    self.update_config = UpdateConfig()
    self.finetune_config = FinetuneConfig()
    self.evaluation_config = EvaluationConfig()
    self.stages = {stage.name: stage for stage in pipeline_stages(self.config.second_iteration)}
    self._keys: dict[str, Any] = {}
    self._nerfs: dict[int, evaluate.TrainedRun] = {}

  # Inputs ------------------------------------------------------------------------------------

  @functools.cached_property
  def original_run_dir(self) -> Path:
    return Path(self.config.original_run) if self.config.original_run else self.directory.path(
        "original")

  @functools.cached_property
  def data_options(self) -> dict[str, Any]:
    """{"root", "downscale"}: from EditConfig.data, else as the given run recorded them."""
    if self.config.data:
      if not Path(self.config.data).is_dir():
        raise InputError("dataset directory not found", self.config.data, "EditConfig.data")
      return {"root": str(Path(self.config.data).resolve()), "downscale": self.config.downscale}
    if self.config.original_run:
      _, description = train.read_model_file(self.config.original_run)
      options = dict(description.get("data_options") or {})
      if "root" not in options:
        raise InputError("the run does not record its dataset; pass --data",
                         self.config.original_run, "data_options")
      return options
    raise InputError("an edit needs a dataset (--data) or a trained NeRF run (--run)",
                     field="EditConfig.data")

  def load_split(self, split: str) -> Dataset:
    options = dict(self.data_options)
    return load_dataset(options.pop("root"), split=split, **options)

  @functools.cached_property
  def dataset(self) -> Dataset:
    """The training views: what the NeRF was trained on and what the edit updates."""
    return self.load_split("train")

  @functools.cached_property
  def eval_cameras(self) -> camera_lib.Cameras:
    """Held-out cameras, where background preservation is measured."""
    return self.load_split("eval").cameras

  @functools.cached_property
  def selection(self) -> select_lib.EditSelection:
    return select_lib.build_selection(self.selection_config, self.dataset)

  @functools.cached_property
  def tile_size(self) -> int:
    return self.sheet_config.tile_size or generation.native_tile_size(self.config.model)

  @functools.cached_property
  def layout(self) -> sheet_lib.SheetLayout:
    config = self.sheet_config
    return sheet_lib.SheetLayout(config.rows, config.columns, config.slot_row,
                                 config.slot_column, self.tile_size, self.tile_size)

  def nerf_dir(self, iteration: int) -> Path:
    """The original NeRF's run (iteration 0) or the edited NeRF's of an iteration."""
    return self.original_run_dir if iteration == 0 else self.directory.path(
        "edited", iteration=iteration)

  def nerf(self, iteration: int) -> evaluate.TrainedRun:
    """The original NeRF (iteration 0) or the edited NeRF of an iteration, loaded once."""
    if iteration not in self._nerfs:
      run_dir = self.nerf_dir(iteration)
      if not checkpoint.has_checkpoint(run_dir):
        raise InputError("no trained NeRF here (run the earlier stages first)", run_dir)
      self._nerfs[iteration] = evaluate.load_run(run_dir)
    return self._nerfs[iteration]

  def generation_options(self, iteration: int) -> pipeline_lib.GenerationOptions:
    scope = "first_iteration" if iteration == 1 else "second_iteration"
    return _scoped(scope, pipeline_lib.GenerationOptions)

  @functools.cached_property
  def _base_generator(self) -> generation.Generator:
    config = self.config
    return generation.load_generator(config.model, config.controlnet, config.scheduler_kind,
                                     config.prompt, config.negative_prompt,
                                     self.generation_options(1),
                                     self.update_config.views_per_device)

  def generator(self, iteration: int) -> generation.Generator:
    return dataclasses.replace(self._base_generator, options=self.generation_options(iteration))

  def conditioning_of_views(self) -> conditioning_lib.Conditioning:
    """The training views' conditioning as the views stage wrote it (all views)."""
    return conditioning_lib.Conditioning.stack(
        [conditioning_lib.Conditioning(**load_arrays(self._view_path(index)))
         for index in range(self.dataset.num_images)])

  def _view_path(self, index: int) -> Path:
    return self.directory.path("views", f"{frame_name(index)}.npz")

  def visible_views(self) -> np.ndarray:
    return np.asarray(files.read_json(self.directory.path("views", "views.json"))["visible"])

  def tile_boxes(self, cameras: camera_lib.Cameras) -> np.ndarray:
    config = self.sheet_config
    points = self.selection.points if config.crops else None
    return update_lib.tile_boxes(cameras, self.layout, points, config.crop_margin,
                                 config.crop_max_upscale)

  # Keys --------------------------------------------------------------------------------------

  def generation_key(self, iteration: int) -> dict[str, Any]:
    config = self.config
    return {"prompt": config.prompt, "negative_prompt": config.negative_prompt,
            "model": config.model, "controlnet": config.controlnet,
            "scheduler_kind": config.scheduler_kind,
            "options": as_json(self.generation_options(iteration))}

  def key(self, name: str) -> Any:
    """The stage's settings and the keys of the stages it builds on (see the module docstring)."""
    if name not in self._keys:
      stage = self.stages[name]
      self._keys[name] = {"settings": stage.settings(self),
                          "after": {before: self.key(before) for before in stage.after}}
    return self._keys[name]


# --------------------------------------------------------------------------------------------
# Stages.


def _original_settings(run: EditRun) -> dict[str, Any]:
  if run.config.original_run:
    return {"original_run": str(Path(run.config.original_run).resolve())}
  return {"data": run.data_options, "train": as_json(_scoped("original", train.TrainConfig)),
          "capacity": gin.get_bindings("derive_capacity")}


def train_original(run: EditRun) -> str:
  if run.config.original_run:
    trained = run.nerf(0)
    return (f"using the trained NeRF {run.original_run_dir} (step {trained.step}, "
            f"{trained.seconds_trained:.0f} s trained)")
  trainer = train.train(run.dataset, run.original_run_dir,
                        config=_scoped("original", train.TrainConfig),
                        data_options=run.data_options, progress=run.progress)
  return (f"{trainer.step} steps ({trainer.seconds_trained:.0f} s) on {run.dataset.num_images} "
          f"views, last batch {trainer.last_statistics.get('psnr', float('nan')):.2f} dB: "
          f"{run.original_run_dir}")


def select(run: EditRun) -> str:
  written = select_lib.write_selection(run.directory.path("selection"), run.selection)
  seeing = reference_cameras.cameras_seeing(run.dataset.cameras, run.selection.points)
  center, radius = run.selection.sphere()
  what = (f"box {np.round(run.selection.bounds, 3).tolist()}" if run.selection.kind == "box"
          else f"proxy {Path(run.selection.proxy.source).name} "
               f"({len(run.selection.proxy.faces)} triangles)")
  return (f"{what} around {np.round(center, 3).tolist()} (radius {radius:.3f}), in view of "
          f"{int(seeing.sum())} of {len(seeing)} cameras: {', '.join(map(str, written))}")


def condition_views(run: EditRun) -> str:
  dataset, original = run.dataset, run.nerf(0)
  indices = np.arange(dataset.num_images)
  for start in range(0, len(indices), VIEWS_PER_CHUNK):
    chunk = [index for index in indices[start:start + VIEWS_PER_CHUNK]
             if not run._view_path(index).is_file()]
    if not chunk:
      continue
    conditioned = conditioning_lib.condition_views(original.model, original.variables,
                                                   dataset.cameras, chunk, run.selection,
                                                   run.selection_config, VIEWS_PER_CHUNK)
    for position, index in enumerate(chunk):
      save_arrays(run._view_path(index), **{name: array[position] for name, array
                                            in conditioned.arrays().items()})
  mask_pixels = np.asarray([np.count_nonzero(load_arrays(run._view_path(index))["mask"])
                            for index in indices])
  empty = masks_lib.views_with_empty_masks(mask_pixels[:, None, None]
                                           >= run.selection_config.min_mask_pixels)
  visible = np.setdiff1d(indices, empty)
  files.write_json(run.directory.path("views", "views.json"),
                   {"visible": visible, "empty": empty, "mask_pixels": mask_pixels})
  skipped = f", {len(empty)} do not see the selection and stay as they are" if len(empty) else ""
  return (f"{dataset.num_images} training views conditioned from the original NeRF, "
          f"{len(visible)} show the selection{skipped}: {run.directory.path('views')}")


def _reference_settings(run: EditRun) -> dict[str, Any]:
  return {"sheet": as_json(run.sheet_config), "model": run.config.model,
          "placement": gin.get_bindings("place_reference_cameras")}


def _read_reference_cameras(path: str, count: int, tile_size: int) -> camera_lib.Cameras:
  """User-given reference cameras: a Blender-style JSON (camera_angle_x, frames)."""
  meta = files.read_json(path)
  frames = meta.get("frames") if isinstance(meta, dict) else None
  if not isinstance(frames, list) or len(frames) != count:
    raise InputError(f"needs exactly {count} frames (one per sheet tile)", path, "frames")
  angle = meta.get("camera_angle_x")
  if isinstance(angle, bool) or not isinstance(angle, (int, float)) or not 0 < angle < np.pi:
    raise InputError(f"must be a field of view in (0, pi) radians, got {angle!r}", path,
                     "camera_angle_x")
  from signerf_jax.data import poses  # pylint: disable=g-import-not-at-top
  camera_to_world = np.stack([poses.check_camera_to_world(frame.get("transform_matrix"), path,
                                                          f"frames[{index}].transform_matrix")
                              for index, frame in enumerate(frames)])
  focal = 0.5 * tile_size / np.tan(angle / 2)
  return camera_lib.Cameras.create(camera_to_world, focal, width=tile_size, height=tile_size)


def render_reference(run: EditRun, iteration: int = 1) -> str:
  layout, directory = run.layout, run.directory.path("reference", iteration=iteration)
  if iteration == 1:
    if run.sheet_config.reference_cameras:
      cameras = _read_reference_cameras(run.sheet_config.reference_cameras, layout.num_tiles,
                                        run.tile_size)
      report = reference_cameras.describe_reference_cameras(cameras, run.dataset.cameras,
                                                            run.selection.points)
    else:
      cameras, report = reference_cameras.place_reference_cameras(
          run.dataset.cameras, run.selection.points, count=layout.num_tiles,
          width=run.tile_size, height=run.tile_size)
    nerf = run.nerf(0)
  else:  # The cameras, masks and control of iteration 1; colour from the edited NeRF.
    first = load_arrays(run.directory.path("reference", "inputs.npz"))
    cameras = _cameras_from_json(files.read_json(run.directory.path("reference",
                                                                    "cameras.json")))
    report = None
    nerf = run.nerf(iteration - 1)
  conditioned = conditioning_lib.condition(nerf.model, nerf.variables, cameras, run.selection,
                                           run.selection_config)
  arrays = conditioned.arrays()
  if iteration > 1:
    arrays.update({name: first[name] for name in ("selected", "mask", "control",
                                                  "control_depth")})
  save_arrays(directory / "inputs.npz", **arrays)
  files.write_json(directory / "cameras.json", {
      "camera_to_world": np.asarray(cameras.camera_to_world), "fx": np.asarray(cameras.fx),
      "fy": np.asarray(cameras.fy), "width": cameras.width, "height": cameras.height,
      "report": None if report is None else report.to_json()})
  tiles_png = directory / "tiles.png"
  files.write_image(tiles_png, figures.image_grid(
      [list(arrays["render"]), list(arrays["mask"]), list(arrays["control"])],
      [[f"tile {index}" for index in range(layout.num_tiles)], ["mask"] * layout.num_tiles,
       ["control"] * layout.num_tiles]))
  fill = "" if report is None else (
      f", selection fills {np.min(report.fill_ratio):.0%}-{np.max(report.fill_ratio):.0%} of "
      "the frames")
  source = "edited" if iteration > 1 else "original"
  return (f"{layout.num_tiles} reference views of {run.tile_size} px rendered from the {source} "
          f"NeRF{fill}: {tiles_png}")


def _cameras_from_json(value: dict[str, Any]) -> camera_lib.Cameras:
  return camera_lib.Cameras.create(np.asarray(value["camera_to_world"]), np.asarray(value["fx"]),
                                   np.asarray(value["fy"]), width=value["width"],
                                   height=value["height"])


def sheet_inputs(run: EditRun, iteration: int) -> generation.SheetInputs:
  tiles = load_arrays(run.directory.path("reference", "inputs.npz", iteration=iteration))
  return generation.SheetInputs.from_tiles(tiles["render"], tiles["control"], tiles["mask"],
                                           run.layout)


def _candidate_path(run: EditRun, recipe: generation.SheetRecipe) -> Path:
  return run.directory.path("preview", "candidates", f"{recipe.file_stem}.npz")


def _known_candidate(run: EditRun):
  """A lookup of preview candidates made with the current reference inputs and settings."""
  expected = canonical_json(run.key("sheet")["after"]) + canonical_json(run.generation_key(1))

  def known(recipe: generation.SheetRecipe) -> np.ndarray | None:
    path = _candidate_path(run, recipe)
    if not path.is_file():
      return None
    stored = load_arrays(path)
    return stored["rgb"] if str(stored["key"]) == expected else None

  return known, expected


def _preview_recipes(run: EditRun) -> list[generation.SheetRecipe]:
  config = run.preview_config
  texts = [str(seed) for seed in config.seeds] + list(config.recipes)
  return [generation.SheetRecipe.parse(text) for text in dict.fromkeys(texts)]


def preview(run: EditRun) -> str:
  recipes = _preview_recipes(run)
  known, key = _known_candidate(run)
  inputs = sheet_inputs(run, 1)
  sheets = generation.generate_sheets(run.generator(1), inputs, recipes, known)
  for recipe, sheet in sheets.items():
    path = _candidate_path(run, recipe)
    if known(recipe) is None:
      save_arrays(path, rgb=sheet, key=np.asarray(key))
      files.write_image(path.with_suffix(".png"), sheet)
  preview_png = run.directory.path("preview", "preview.png")
  files.write_image(run.directory.path("preview", "inputs.png"), figures.image_grid(
      [[inputs.rgb, inputs.mask, inputs.control]], [["reference renders", "masks", "control"]]))
  files.write_image(preview_png, figures.image_grid(
      [[sheets[recipe] for recipe in recipes]], [[f"sheet {recipe}" for recipe in recipes]]))
  return (f"{len(recipes)} candidate sheets ({', '.join(map(str, recipes))}) side by side: "
          f"{preview_png}; pick one with --sheet RECIPE, re-roll tiles with --reroll "
          "SEED/TILE,TILE@NEWSEED")


def _sheet_settings(run: EditRun, iteration: int) -> dict[str, Any]:
  return {"recipe": run.config.sheet_recipe(iteration),
          "generation": run.generation_key(iteration)}


def generate_sheet(run: EditRun, iteration: int = 1) -> str:
  recipe = generation.SheetRecipe.parse(run.config.sheet_recipe(iteration))
  inputs = sheet_inputs(run, iteration)
  known = _known_candidate(run)[0] if iteration == 1 else (lambda recipe: None)
  reused = known(recipe) is not None
  sheet = generation.generate_sheets(run.generator(iteration), inputs, [recipe], known)[recipe]
  directory = run.directory.path("sheet", iteration=iteration)
  save_arrays(directory / "sheet.npz", rgb=sheet, control=inputs.control, mask=inputs.mask,
              recipe=np.asarray(str(recipe)))
  files.write_image(directory / "sheet.png", sheet)
  how = "taken from the preview" if reused else "generated"
  return f"sheet {recipe} {how}: {directory / 'sheet.png'}"


def _update_settings(run: EditRun, iteration: int) -> dict[str, Any]:
  config = run.sheet_config
  return {"seed": run.config.seed, "generation": run.generation_key(iteration),
          "crops": config.crops, "crop_margin": config.crop_margin,
          "crop_max_upscale": config.crop_max_upscale}


def update_image_set(run: EditRun, iteration: int = 1) -> str:
  dataset = run.dataset
  sheet = load_arrays(run.directory.path("sheet", "sheet.npz", iteration=iteration))
  boxes = run.tile_boxes(dataset.cameras)
  edited_nerf = run.nerf(iteration - 1) if iteration > 1 else None

  def load_views(indices: np.ndarray) -> update_lib.SlotViews:
    conditioned = [load_arrays(run._view_path(int(index))) for index in indices]
    masks = np.stack([item["mask"] for item in conditioned])
    images = dataset.images[indices]
    if edited_nerf is not None:
      # Iteration 2 updates what the edited NeRF shows in the selection, the photo elsewhere.
      rendered = render.render_cameras(edited_nerf.model, edited_nerf.variables,
                                       dataset.cameras.take(indices))["rgb"]
      images = images * (1 - masks[..., None]) + rendered * masks[..., None]
    return update_lib.SlotViews(images=images, masks=masks,
                                controls=np.stack([item["control"] for item in conditioned]),
                                boxes=boxes[indices])

  visible = run.visible_views()
  generator = run.generator(iteration)
  directory = run.directory.path("update", iteration=iteration)
  report = update_lib.run_update(generator, sheet["rgb"], sheet["control"], run.layout, visible,
                                 load_views, directory, run.config.seed, progress=run.progress)
  skipped = dataset.num_images - len(visible)
  resumed = f", {report['resumed']} done before" if report["resumed"] else ""
  return (f"{len(visible)} views inpainted in the slot of sheet {sheet['recipe']} "
          f"({report['batches']} batches of {report['batch_size']} on {report['devices']} "
          f"device(s){resumed}), {skipped} without the selection left as they are: "
          f"{directory / update_lib.IMAGES_FOLDER}")


def _provenance(run: EditRun, iteration: int) -> dict[str, Any]:
  config = run.config
  model = directory_fingerprint(config.model)
  return {
      "tool": "signerf_jax.editing", "iteration": iteration, "prompt": config.prompt,
      "negative_prompt": config.negative_prompt, "seed": config.seed,
      "sheet": config.sheet_recipe(iteration), "selection": as_json(run.selection_config),
      "selection_scene_frame": run.selection.describe(),
      "generation": as_json(run.generation_options(iteration)),
      "sheet_layout": as_json(run.sheet_config), "tile_size": run.tile_size,
      "model": model,
      "controlnet": directory_fingerprint(config.controlnet) if config.controlnet else None,
      "source_dataset": run.data_options, "original_nerf": str(run.original_run_dir.resolve()),
      "unedited_views": np.setdiff1d(np.arange(run.dataset.num_images),
                                     run.visible_views()).tolist(),
      "gin_config": gin.config_str(),
  }


def write_dataset(run: EditRun, iteration: int = 1) -> str:
  dataset = run.dataset
  conditioned = run.conditioning_of_views()
  images = dataset.images.copy()
  for index in run.visible_views():
    images[index] = files.read_image(update_lib.edited_image_path(
        run.directory.path("update", iteration=iteration), int(index)))[..., :3]
  directory = run.directory.path("dataset", iteration=iteration)
  transforms = edited_dataset.write_edited_dataset(
      directory, dataset, images, conditioned.mask, conditioned.control,
      conditioned.control_depth, _provenance(run, iteration))
  return (f"{dataset.num_images} views (originals, masks, control depth alongside) in nerfstudio "
          f"format: {transforms}")


def _nerf_update_method(run: EditRun, iteration: int) -> str:
  """"finetune" or "retrain"; a second iteration always fine-tunes the edited NeRF."""
  if iteration > 1:
    return "finetune"
  if run.config.nerf_update != "auto":
    return run.config.nerf_update
  return "retrain" if run.selection_config.kind == "proxy" else "finetune"


def _finetune_settings(run: EditRun, iteration: int) -> dict[str, Any]:
  method = _nerf_update_method(run, iteration)
  return {"method": method, "losses": as_json(run.finetune_config),
          "train": as_json(_scoped(method, train.TrainConfig))}


def update_nerf(run: EditRun, iteration: int = 1) -> str:
  method = _nerf_update_method(run, iteration)
  dataset_dir = run.directory.path("dataset", iteration=iteration)
  edited = load_dataset(dataset_dir, split="all")
  run_dir = run.directory.path("edited", iteration=iteration)
  data_options = {"root": str(dataset_dir.resolve()), "downscale": 1}
  config = _scoped(method, train.TrainConfig)
  start = run.nerf(iteration - 1)
  model, init_variables = start.model, start.variables
  if run.finetune_config.edit_region and model.edit_region is None:
    model = dataclasses.replace(model, edit_region=run.selection.grown_bounds(
        run.finetune_config.region_margin))
    init_variables = {"params": start.variables["params"], "original": start.variables}
  region = "" if model.edit_region is None else (
      ", inside the box " + " .. ".join(str(np.round(corner, 3).tolist())
                                        for corner in model.edit_region) +
      " only (the original NeRF elsewhere)")
  if method == "retrain":
    # A new field (over the original one outside the edit region); without an edit region a
    # new NeRF built for the edited dataset, as for any dataset.
    kept = {"original": init_variables["original"]} if model.edit_region is not None else None
    trainer = train.train(edited, run_dir, config=config, data_options=data_options,
                          model=model if kept else None, init_variables=kept,
                          progress=run.progress)
    how = "retrained from scratch"
  else:
    losses = finetune.FinetuneLosses(
        lpips_weight=run.finetune_config.lpips_weight if run.finetune_config.lpips_weights
        else 0.0, patch_size=run.finetune_config.patch_size)
    trainer = finetune.finetune(
        edited, run_dir, model=model, init_variables=init_variables, config=config,
        loss_settings=losses, lpips_params=finetune.load_lpips(run.finetune_config.lpips_weights),
        edited_bounds=model.edit_region or run.selection.bounds, data_options=data_options,
        progress=run.progress)
    how = ("fine-tuned from the " + ("original" if iteration == 1 else "edited") +
           " NeRF (L1" + (" + LPIPS)" if losses.uses_lpips else ")"))
  run._nerfs.pop(iteration, None)  # pylint: disable=protected-access
  return (f"{how}{region}: {trainer.step} steps ({trainer.seconds_trained:.0f} s), last batch "
          f"{trainer.last_statistics.get('psnr', float('nan')):.2f} dB: {run_dir}")


def _evaluation_settings(run: EditRun) -> dict[str, Any]:
  return {"evaluation": as_json(run.evaluation_config), "generation": run.generation_key(1)}


def _evenly_spaced(indices: np.ndarray, count: int) -> np.ndarray:
  if count >= len(indices):
    return indices
  return indices[np.round(np.linspace(0, len(indices) - 1, count)).astype(int)]


def evaluate_edit(run: EditRun) -> str:
  config, directory = run.evaluation_config, run.directory.path("evaluation")
  final_iteration = 2 if run.config.second_iteration else 1
  original, edited = run.nerf(0), run.nerf(final_iteration)
  cameras = run.eval_cameras
  before = conditioning_lib.Conditioning.stack_chunks([
      conditioning_lib.condition_views(original.model, original.variables, cameras, chunk,
                                       run.selection, run.selection_config, VIEWS_PER_CHUNK)
      for chunk in np.array_split(np.arange(cameras.num_cameras),
                                  -(-cameras.num_cameras // VIEWS_PER_CHUNK))])
  after = render.render_cameras(edited.model, edited.variables, cameras)["rgb"]
  metrics: dict[str, Any] = {"prompt": run.config.prompt, "num_eval_views": cameras.num_cameras}
  metrics["background"] = background.background_preservation(before.render, after,
                                                              before.mask > 0)

  # The image sets: original training images, the sheet-propagated edit, independent edits.
  dataset = run.dataset
  update_dir = run.directory.path("update", iteration=final_iteration)
  visible = run.visible_views()
  edited_images = np.stack([files.read_image(update_lib.edited_image_path(update_dir, int(index)))
                            [..., :3] for index in visible])
  conditioned = run.conditioning_of_views()
  selected, masks = conditioned.selected[visible], conditioned.mask[visible]
  metrics["prompt_color_adherence"] = {
      "image_set": evaluation.prompt_color_adherence(run.config.prompt, edited_images, selected),
      "nerf_renders": evaluation.prompt_color_adherence(run.config.prompt, after,
                                                        before.selected)}
  if run.selection.kind == "proxy":
    metrics["shape_iou"] = {
        "image_set": evaluation.shape_adherence(dataset.images[visible], edited_images,
                                                selected, masks),
        "nerf_renders": evaluation.shape_adherence(before.render, after, before.selected,
                                                   before.mask)}
  if config.independent_views:
    chosen = _evenly_spaced(np.arange(len(visible)), config.independent_views)
    views = update_lib.SlotViews(dataset.images[visible[chosen]], masks[chosen],
                                 conditioned.control[visible[chosen]],
                                 run.tile_boxes(dataset.cameras)[visible[chosen]])
    # Same prompt, settings and seed for every view, as the paper's comparison.
    keys = np.repeat(generation.seed_key(run.config.seed)[None], len(chosen), axis=0)
    start = time.perf_counter()
    independent = evaluation.independent_edits(run.generator(1), run.layout, views, keys)
    # Their cost against the sheet propagation's (the ablations' quality against time).
    metrics["independent_edits"] = {"views": len(chosen),
                                    "seconds": time.perf_counter() - start}
    metrics["consistency"] = evaluation.consistency_comparison(
        {"original": views.images, "sheet_propagated": edited_images[chosen],
         "independent": independent},
        dataset.cameras.take(visible[chosen]), masks[chosen] > 0)
    files.write_image(directory / "independent_edits.png", figures.image_grid(
        [list(views.images[:6]), list(edited_images[chosen][:6]), list(independent[:6])],
        [["original"] * min(6, len(chosen)), ["sheet propagated"] * min(6, len(chosen)),
         ["independent"] * min(6, len(chosen))]))
  if config.clip_model:
    model = clip_similarity.load_clip_model(config.clip_model)
    captions = (config.source_caption, run.config.prompt)
    metrics["clip_directional_similarity"] = {
        "image": float(np.mean(clip_similarity.clip_directional_similarity(
            model, dataset.images[visible], edited_images, *captions))),
        "nerf": float(np.mean(clip_similarity.clip_directional_similarity(
            model, before.render, after, *captions)))}

  # Figures: before/after at the eval cameras showing the most of the selection, the sheet, video.
  shown = np.argsort(-np.count_nonzero(before.selected.reshape(len(after), -1), axis=1),
                     kind="stable")[:BEFORE_AFTER_VIEWS]
  files.write_image(directory / "before_after.png", figures.image_grid(
      [[before.render[index] for index in shown], [after[index] for index in shown]],
      [["before"] * len(shown), ["after"] * len(shown)]))
  sheet_png = run.directory.path("sheet", "sheet.png", iteration=final_iteration)
  shutil.copyfile(sheet_png, directory / "sheet.png")
  outputs = [directory / "before_after.png", directory / "sheet.png"]
  if config.video_frames:
    path = render.orbit_cameras(edited.model, dataset.cameras, config.video_frames)
    frames = np.concatenate([render.render_cameras(nerf.model, nerf.variables, path)["rgb"]
                             for nerf in (original, edited)], axis=2)
    outputs.append(render.write_video(directory / "before_after.mp4", frames, config.video_fps))
  metrics["stage_seconds"] = run.directory.stage_seconds()
  files.write_json(directory / "metrics.json", metrics)
  outputs.insert(0, directory / "metrics.json")
  bg = metrics["background"]
  return (f"background PSNR {bg['psnr_paper']:.2f} dB / SSIM {bg['ssim_paper']:.3f} (paper's "
          f"masked images; background only: {bg['psnr_background']:.2f} dB) on "
          f"{cameras.num_cameras} held-out views: {', '.join(map(str, outputs))}")


# --------------------------------------------------------------------------------------------
# The runner.


@dataclasses.dataclass(frozen=True)
class Stage:
  """A pipeline stage.

  Attributes:
    name: as in stages.json and `run_edit(until=...)`.
    run: does the work; returns the one-line summary.
    settings: what the stage reads (part of its key).
    after: the stages whose outputs it uses (their keys are part of its key).
    outputs: the folders it writes, cleared when the stage is redone with another key.
    description: what it does, shown while it runs.
  """

  name: str
  run: Callable[[EditRun], str]
  settings: Callable[[EditRun], Any]
  after: tuple[str, ...]
  outputs: Callable[[EditRun], tuple[Path, ...]]
  description: str


def _for_iteration(function: Callable, iteration: int) -> Callable[[EditRun], Any]:
  return lambda run: function(run, iteration)


def _folders(*names: str, iteration: int = 1) -> Callable[[EditRun], tuple[Path, ...]]:
  return lambda run: tuple(run.directory.path(name, iteration=iteration) for name in names)


def _iteration_stages(iteration: int) -> list[Stage]:
  """Steps 4-7 of one iteration (the second starts from the first's edited NeRF)."""
  suffix = "" if iteration == 1 else f"_{iteration}"
  previous = ("finetune",) if iteration == 2 else ()
  stages = [Stage(f"reference{suffix}", _for_iteration(render_reference, iteration),
                  _reference_settings, ("original", "select") + previous +
                  (("reference",) if previous else ()), _folders("reference", iteration=iteration),
                  "placing the reference cameras and rendering their tiles")]
  if iteration == 1:
    stages.append(Stage("preview", preview, lambda run: {
        "recipes": [str(recipe) for recipe in _preview_recipes(run)],
        "generation": run.generation_key(1)}, ("reference",), lambda run: (),
                        "generating candidate sheets"))
  return stages + [
      Stage(f"sheet{suffix}", _for_iteration(generate_sheet, iteration),
            _for_iteration(_sheet_settings, iteration), (f"reference{suffix}",),
            _folders("sheet", iteration=iteration), "generating the chosen sheet"),
      Stage(f"update{suffix}", _for_iteration(update_image_set, iteration),
            _for_iteration(_update_settings, iteration), (f"sheet{suffix}", "views") + previous,
            _folders("update", iteration=iteration),
            "updating every view through the sheet's slot"),
      Stage(f"dataset{suffix}", _for_iteration(write_dataset, iteration), lambda run: {},
            (f"update{suffix}",), _folders("dataset", iteration=iteration),
            "writing the edited dataset"),
      Stage(f"finetune{suffix}", _for_iteration(update_nerf, iteration),
            _for_iteration(_finetune_settings, iteration),
            (f"dataset{suffix}",) + (previous or ("original",)),
            _folders("edited", iteration=iteration), "updating the NeRF on the edited views"),
  ]


def pipeline_stages(second_iteration: bool) -> list[Stage]:
  """The stages in order (with the second iteration's when enabled)."""
  stages = [
      Stage("original", train_original, _original_settings, (),
            lambda run: () if run.config.original_run else (run.original_run_dir,),
            "training the original NeRF"),
      Stage("select", select, lambda run: as_json(run.selection_config), ("original",),
            _folders("selection"), "building the selection"),
      Stage("views", condition_views, lambda run: {}, ("original", "select"), _folders("views"),
            "rendering masks and control depth of every training view"),
  ]
  stages += _iteration_stages(1)
  if second_iteration:
    stages += _iteration_stages(2)
  final = "finetune_2" if second_iteration else "finetune"
  stages.append(Stage("evaluate", evaluate_edit, _evaluation_settings, (final, "views"),
                      _folders("evaluation"), "evaluating the edit"))
  return stages


def _prepare_folder(path: Path, key: Any) -> None:
  """Clears `path` unless it holds the outputs of a run with this key; marks it with the key.

  The same key means an interrupted run of the same stage: its finished files are kept.
  """
  marker = path / STAGE_KEY_FILE
  current = canonical_json(key)
  if path.is_dir() and (not marker.is_file() or marker.read_text() != current):
    shutil.rmtree(path)
  path.mkdir(parents=True, exist_ok=True)
  if not marker.is_file():
    files.write_text(marker, current)


def _with_dependents(stages: list[Stage], names) -> set[str]:
  """`names` and every stage that builds on one of them, directly or not."""
  chosen = set(names)
  for stage in stages:
    if chosen.intersection(stage.after):
      chosen.add(stage.name)
  return chosen


def run_edit(directory, until: str = "evaluate", redo: tuple[str, ...] = (),
             progress: bool = True, log: Callable[[str], None] = print) -> EditRun:
  """Runs (or resumes) the pipeline in `directory` up to and including stage `until`, with the
  current gin bindings (saved to `directory`/config.gin).

  Args:
    until: the last stage to run.
    redo: stages to run again from scratch even when their key is current (with every stage
      that builds on them).
    progress: show progress bars.
    log: receives one line as each stage starts and ends.
  """
  run = EditRun(directory, progress)
  stages = list(run.stages.values())
  names = [stage.name for stage in stages]
  for name in (until, *redo):
    if name not in names:
      raise InputError(f"unknown stage {name!r} (stages: {', '.join(names)})", field="stage")
  run.directory.root.mkdir(parents=True, exist_ok=True)
  configs.save_gin_config(run.directory.root)
  redone = _with_dependents(stages, redo)
  for stage in stages:
    if stage.name in redone:
      for folder in stage.outputs(run):
        shutil.rmtree(folder, ignore_errors=True)
  run.directory.forget(redone)
  stages = stages[:names.index(until) + 1]
  for number, stage in enumerate(stages, 1):
    key = run.key(stage.name)
    label = f"[{number}/{len(stages)}] {stage.name}"
    if run.directory.is_finished(stage.name, key):
      log(f"{label}: done before - {run.directory.record(stage.name).summary}")
      continue
    log(f"{label}: {stage.description} ...")
    for folder in stage.outputs(run):
      _prepare_folder(folder, key)
    start = time.perf_counter()
    summary = stage.run(run)
    seconds = time.perf_counter() - start
    run.directory.finish(stage.name, key, seconds, summary)
    log(f"{label}: {summary} ({seconds:.1f} s)")
  return run
