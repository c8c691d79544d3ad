"""What every stage reads: the edit directory, the settings, and the inputs earlier stages made.

`EditContext` is built once per run by the runner. Its inputs (the dataset, the selection, the
trained NeRFs, the generator) are loaded on first use and kept, so stages that share an input
load it once. Everything a stage writes goes to the edit directory; later stages read it back
through the accessors here, never through another stage's code.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from signerf_jax import camera as camera_lib
from signerf_jax import checkpoints, files
from signerf_jax.data import load_dataset, load_views
from signerf_jax.data.dataset import Dataset, SceneViews
from signerf_jax.editing import conditioning as conditioning_lib
from signerf_jax.editing import generation
from signerf_jax.editing import select as select_lib
from signerf_jax.editing import sheet as sheet_lib
from signerf_jax.editing import update as update_lib
from signerf_jax.editing.config import EditSettings, as_json
from signerf_jax.editing.project import EditDirectory, frame_name, load_arrays
from signerf_jax.errors import InputError
from signerf_jax.nerf import evaluate, training_run


@dataclasses.dataclass(frozen=True)
class EditContext:
  """One edit's directory, settings and (loaded on first use) inputs.

  Attributes:
    directory: the edit directory.
    settings: everything the edit reads.
    progress: show progress bars.
    keys: each stage's key (`runner.stage_keys`), for stages whose outputs record what made
      them (the preview's candidates).
    stages_to_run: the stages this command runs (not those whose results it reuses), so that
      a stage can compile a program a later one reuses (the preview's sampler, the update's).
  """

  directory: EditDirectory
  settings: EditSettings
  progress: bool = True
  keys: Mapping[str, Any] = dataclasses.field(default_factory=dict)
  stages_to_run: tuple[str, ...] = ()
  # Trained NeRFs by iteration (0: the original), loaded once; dropped when a stage retrains.
  _nerfs: dict[int, evaluate.TrainedRun] = dataclasses.field(default_factory=dict, repr=False,
                                                             compare=False)

  # The dataset and the selection -------------------------------------------------------------

  @functools.cached_property
  def original_run_dir(self) -> Path:
    run = self.settings.edit.original_run
    return Path(run) if run else self.directory.path("original")

  @functools.cached_property
  def data_options(self) -> dict[str, Any]:
    """{"root", "downscale"}: from EditConfig.data, else as the given run recorded them."""
    config = self.settings.edit
    if config.data:
      if not Path(config.data).is_dir():
        raise InputError("dataset directory not found", config.data, "EditConfig.data")
      return {"root": str(Path(config.data).resolve()), "downscale": config.downscale}
    if config.original_run:
      _, description = training_run.read_model_file(config.original_run)
      options = dict(description.get("data_options") or {})
      if "root" not in options:
        raise InputError("the run does not record its dataset; pass --data", config.original_run,
                         "data_options")
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
  def views(self) -> SceneViews:
    """The training views' cameras and scene frame: all the selection and the reference cameras
    need, read in milliseconds without decoding the images (seconds for a real capture; the
    preview needs no pixel)."""
    options = dict(self.data_options)
    return load_views(options.pop("root"), split="train", **options)

  @functools.cached_property
  def eval_cameras(self) -> camera_lib.Cameras:
    """Held-out cameras, where background preservation is measured."""
    return self.load_split("eval").cameras

  @functools.cached_property
  def selection(self) -> select_lib.EditSelection:
    return select_lib.build_selection(self.settings.selection, self.views)

  # The NeRFs ---------------------------------------------------------------------------------

  def nerf_dir(self, iteration: int) -> Path:
    """The original NeRF's run (iteration 0) or the edited NeRF's of an iteration."""
    return self.original_run_dir if iteration == 0 else self.directory.path(
        "edited", iteration=iteration)

  def replayed_schedule(self, run_dir: Path) -> np.ndarray | None:
    """[S] float32 progress per step of the training that `EditConfig.replay`'s edit did into
    the same place as `run_dir` (inside this edit), or None when not replaying.

    Raises:
      InputError: the earlier edit holds no schedule there.
    """
    replay = self.settings.edit.replay
    if not replay:
      return None
    counterpart = Path(replay) / run_dir.relative_to(self.directory.root)
    progress = training_run.read_schedule(counterpart)
    if progress is None:
      raise InputError("holds no schedule.json to replay (not a NeRF training of an edit, or "
                       "one from before schedules were recorded)", counterpart, "EditConfig.replay")
    return progress

  def nerf(self, iteration: int) -> evaluate.TrainedRun:
    """The original NeRF (iteration 0) or the edited NeRF of an iteration, loaded once."""
    if iteration not in self._nerfs:
      run_dir = self.nerf_dir(iteration)
      if not checkpoints.has_checkpoint(run_dir):
        raise InputError("no trained NeRF here (run the earlier stages first)", run_dir)
      self._nerfs[iteration] = evaluate.load_run(run_dir)
    return self._nerfs[iteration]

  def forget_nerf(self, iteration: int) -> None:
    """Drops a loaded NeRF (its stage trained it again)."""
    self._nerfs.pop(iteration, None)

  # The sheet and the diffusion model ---------------------------------------------------------

  @functools.cached_property
  def tile_size(self) -> int:
    return self.settings.sheet.tile_size or generation.native_tile_size(self.settings.edit.model)

  @functools.cached_property
  def layout(self) -> sheet_lib.SheetLayout:
    config = self.settings.sheet
    return sheet_lib.SheetLayout(config.rows, config.columns, config.slot_row,
                                 config.slot_column, self.tile_size, self.tile_size)

  def tile_boxes(self, cameras: camera_lib.Cameras) -> np.ndarray:
    """[N, 4] the region of each view that becomes a sheet tile (`update.tile_boxes`)."""
    config = self.settings.sheet
    points = self.selection.points if config.crops else None
    return update_lib.tile_boxes(cameras, self.layout, points, config.crop_margin,
                                 config.crop_max_upscale)

  @functools.cached_property
  def _first_generator(self) -> generation.Generator:
    config, settings = self.settings.edit, self.settings
    return generation.load_generator(config.model, config.controlnet, config.scheduler_kind,
                                     config.prompt, config.negative_prompt,
                                     settings.generation_options(1),
                                     settings.update.views_per_device, settings.attention,
                                     precision=config.diffusion_precision)

  def generator(self, iteration: int) -> generation.Generator:
    """The diffusion model with the prompt and the iteration's options (loaded once)."""
    return dataclasses.replace(self._first_generator,
                               options=self.settings.generation_options(iteration))

  def generation_key(self, iteration: int) -> dict[str, Any]:
    """What the generated images of an iteration depend on besides their inputs."""
    config = self.settings.edit
    return {"prompt": config.prompt, "negative_prompt": config.negative_prompt,
            "model": config.model, "controlnet": config.controlnet,
            "scheduler_kind": config.scheduler_kind, "precision": config.diffusion_precision,
            "options": as_json(self.settings.generation_options(iteration))}

  # What the views stage wrote ----------------------------------------------------------------

  def view_path(self, index: int) -> Path:
    """The conditioning (mask, control depth, ...) of training view `index`."""
    return self.directory.path("views", f"{frame_name(index)}.npz")

  def conditioning_of_views(self) -> conditioning_lib.Conditioning:
    """The training views' conditioning (all views)."""
    return conditioning_lib.Conditioning.stack(
        [load_conditioning(self.view_path(index)) for index in range(self.dataset.num_images)])

  def visible_views(self) -> np.ndarray:
    """[V] int indices of the training views that show the selection."""
    return np.asarray(files.read_json(self.directory.path("views", "views.json"))["visible"])


def load_conditioning(path: Path) -> conditioning_lib.Conditioning:
  """A `Conditioning` saved with `save_arrays(path, **conditioning.arrays())`."""
  names = [field.name for field in dataclasses.fields(conditioning_lib.Conditioning)]
  return conditioning_lib.Conditioning(**load_arrays(path, names))


def evenly_spaced(indices: np.ndarray, count: int) -> np.ndarray:
  """At most `count` of `indices` [N], evenly spaced from the first to the last."""
  if count >= len(indices):
    return indices
  return indices[np.round(np.linspace(0, len(indices) - 1, count)).astype(int)]
