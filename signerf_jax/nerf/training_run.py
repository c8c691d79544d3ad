"""A NeRF training run: its directory, the `Trainer` advancing it, and `train`, the entry point.

A run directory holds:
  config.gin          the gin bindings, written by the command that parsed them (not here)
  model.json          scene geometry, capacity and where the data came from
  checkpoint.msgpack  the latest TrainState plus step / seconds trained (`checkpoints`)
  schedule.json       the schedule's progress at each step so far (`write_schedule`)
A resumed run continues exactly as an uninterrupted one (`train.train_step`'s randomness follows
the step). A time-budgeted run's schedule follows the seconds trained, which no two runs share:
the progress each step was given is recorded, and a run given it back (`replay_progress`)
repeats the first bit for bit on the same kind of machine. The loop itself, with its time
budget and divergence guard, is `training_loop`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from signerf_jax import checkpoints, files, ownership, parallel, training_loop
from signerf_jax.data.dataset import Dataset
from signerf_jax.errors import InputError
from signerf_jax.nerf import keypoint_depth, occupancy, photo_consistency, visual_hull
from signerf_jax.nerf import model as nerf_model
from signerf_jax.nerf.capacity import Capacity, CapacityRules, derive_capacity
from signerf_jax.nerf.scene_info import SceneInfo
from signerf_jax.nerf.capture_choices import can_carve, with_capture_choices
from signerf_jax.nerf.train import (TrainConfig, TrainState, init_state, make_train_step,
                                    upgrade_state_dict)
from signerf_jax.nerf.training_data import TrainingData, with_region_rays

MODEL_FILE = "model.json"
SCHEDULE_FILE = "schedule.json"


@dataclasses.dataclass
class Trainer:
  """A training run in memory: the model, its jitted step and the state, advanced in bursts.

  `train` below is the usual entry point; benchmarks use a Trainer directly to evaluate between
  bursts without recompiling. `mesh` is the devices the steps run on (None: all of them).
  `progress_record` is the float32 progress each step so far was given (None: unknown, for a
  run resumed from a checkpoint without its schedule.json); `replay_progress` ([S] float32),
  when given, is the progress of each step instead of the steps and seconds done.
  """

  model: nerf_model.NerfModel
  config: TrainConfig
  data: TrainingData
  state: TrainState
  seconds_trained: float = 0.0
  samples_trained: float = 0.0
  last_statistics: dict[str, float] = dataclasses.field(default_factory=dict)
  mesh: Mesh | None = None
  progress_record: list[float] | None = dataclasses.field(default_factory=list)
  replay_progress: np.ndarray | None = None

  def __post_init__(self):
    self.mesh = parallel.device_mesh() if self.mesh is None else self.mesh
    self._step_fn = make_train_step(self.model, self.config, self.mesh)
    self.data = with_region_rays(self.data, self.model, self.state.variables)
    # Placed once: the step would otherwise copy the images to every device at each call.
    self.data, self.state = parallel.replicate((self.data, self.state), self.mesh)

  @property
  def step(self) -> int:
    return int(self.state.step)

  @property
  def progress(self) -> float:
    """How far through its schedule the run is, in [0, 1]: the replayed progress of this step,
    else the larger of the steps done over `config.steps` and the seconds trained over
    `config.max_seconds` (when set)."""
    if self.replay_progress is not None:
      return float(self.replay_progress[min(self.step, len(self.replay_progress) - 1)])
    fractions = [self.step / max(self.config.steps, 1)]
    if self.config.max_seconds:
      fractions.append(self.seconds_trained / self.config.max_seconds)
    return min(1.0, max(fractions))

  def run(self, *, until_step: int | None = None, until_seconds: float | None = None,
          run_dir: str | os.PathLike | None = None, progress: bool = True) -> dict[str, float]:
    """Trains until `until_step` (default: config.steps) or `until_seconds` of total training
    time (default: config.max_seconds), checkpointing into `run_dir` (if given) periodically
    and at the end (`training_loop.run_loop`, which also stops a diverged run).

    Returns:
      the last step's statistics (floats).
    """
    def advance(seconds_trained: float) -> dict[str, float]:
      self.seconds_trained = seconds_trained
      progress = jnp.float32(self.progress)
      self.state, statistics = self._step_fn(self.state, self.data, progress)
      if self.progress_record is not None:
        self.progress_record.append(float(progress))
      # Read at once (blocking), so the loop times each step and `progress` follows it.
      statistics = {name: float(value) for name, value in statistics.items()}
      self.samples_trained += statistics["samples"]
      return statistics

    def save(seconds_trained: float) -> None:
      self.seconds_trained = seconds_trained
      self.save(run_dir)

    budget = training_loop.LoopBudget(
        until_step=self.config.steps if until_step is None else until_step,
        max_seconds=until_seconds if until_seconds is not None else self.config.max_seconds,
        checkpoint_every_steps=self.config.checkpoint_every_steps,
        checkpoint_every_seconds=self.config.checkpoint_every_seconds)
    result = training_loop.run_loop(
        advance, None if run_dir is None else save, budget, step=self.step,
        seconds_trained=self.seconds_trained, where=run_dir or "training",
        hint="a lower TrainConfig.learning_rate", progress=progress)
    self.seconds_trained = result.seconds_trained
    self.last_statistics = result.statistics or self.last_statistics
    return self.last_statistics

  def save(self, run_dir: str | os.PathLike) -> None:
    # The schedule first: a kill between the two leaves it longer than the checkpoint's steps,
    # which `restore` cuts, never shorter.
    if self.progress_record is not None:
      write_schedule(run_dir, self.progress_record)
    checkpoints.save(run_dir, self.state, {"step": self.step,
                                          "seconds_trained": self.seconds_trained,
                                          "samples_trained": self.samples_trained})

  def restore(self, run_dir: str | os.PathLike) -> None:
    """Continues from the checkpoint in `run_dir` (state, seconds and samples trained)."""
    state, metadata = checkpoints.restore(run_dir, self.state, upgrade_state_dict)
    # Placed like the fresh state: host arrays would make the first step compile again.
    self.state = parallel.replicate(state, self.mesh)
    self.seconds_trained = float(metadata.get("seconds_trained", 0.0))
    self.samples_trained = float(metadata.get("samples_trained", 0.0))
    record = read_schedule(run_dir)
    self.progress_record = (None if record is None or len(record) < self.step
                            else record[:self.step].tolist())


def write_schedule(run_dir: str | os.PathLike, progress: list[float]) -> None:
  """Writes schedule.json: {"steps": S, "progress": [S] the float32 progress of each step, each
  as the float64 equal to it (JSON keeps a float64 exactly, so it reads back as that float32)}."""
  files.write_json(Path(run_dir) / SCHEDULE_FILE, {
      "steps": len(progress), "progress": [float(np.float32(value)) for value in progress]})


def read_schedule(run_dir: str | os.PathLike) -> np.ndarray | None:
  """[S] float32 progress of each step a run recorded (schedule.json), or None without one.

  Raises:
    InputError naming the file: malformed, or progress outside [0, 1].
  """
  path = Path(run_dir) / SCHEDULE_FILE
  if not path.is_file():
    return None
  record = files.read_json(path)
  try:
    progress = np.asarray(record["progress"], np.float32)
    valid = progress.ndim == 1 and record["steps"] == len(progress)
  except (KeyError, TypeError, ValueError):
    valid = False
  if not valid or not np.all((progress >= 0) & (progress <= 1)):
    raise InputError("must hold \"steps\" and that many \"progress\" values in [0, 1]", path,
                     "progress")
  return progress


def dataset_fingerprint(dataset: Dataset, data_options: dict[str, Any] | None = None
                        ) -> dict[str, Any]:
  """What identifies the data a run trains on: the dataset's folder, its training images (names
  and size), the downscale it was loaded with and a hash of its cameras (poses, intrinsics,
  lens) as loaded."""
  options = data_options or {}
  root = options.get("root") or dataset.root
  cameras = dataset.cameras
  digest = hashlib.sha256()
  for array in (cameras.camera_to_world, cameras.fx, cameras.fy, cameras.cx, cameras.cy,
                cameras.distortion):
    digest.update(np.ascontiguousarray(array, np.float32).tobytes())
  return {"root": str(Path(root).resolve()) if root else None,
          "images": list(dataset.image_names), "size": [dataset.width, dataset.height],
          "downscale": options.get("downscale"), "cameras_sha256": digest.hexdigest()}


def _fingerprint_changes(saved: dict[str, Any], current: dict[str, Any]) -> list[str]:
  """What differs between two fingerprints, in words."""
  changes = []
  if saved.get("root") != current["root"]:
    changes.append(f"the dataset was {saved.get('root')}, now {current['root']}")
  if saved.get("images") != current["images"]:
    before, after = saved.get("images") or [], current["images"]
    changes.append(f"{len(before)} training images then, {len(after)} now"
                   + (", other names" if len(before) == len(after) else ""))
  if saved.get("size") != current["size"]:
    size = lambda value: "x".join(map(str, value or ["?"]))  # noqa: E731
    changes.append(f"images of {size(saved.get('size'))} px then, {size(current['size'])} now")
  if saved.get("downscale") != current["downscale"]:
    changes.append(f"downscale {saved.get('downscale')} then, {current['downscale']} now")
  if not changes and saved.get("cameras_sha256") != current["cameras_sha256"]:
    changes.append("the cameras differ")
  return changes


def data_changes(run_dir: str | os.PathLike, dataset: Dataset,
                 data_options: dict[str, Any] | None = None) -> list[str]:
  """What differs, in words, between the data a run was trained on (its model.json's
  fingerprint) and `dataset` (nothing for a model.json without a fingerprint)."""
  saved = files.read_json(Path(run_dir) / MODEL_FILE).get("fingerprint")
  if not isinstance(saved, dict):
    return []
  return _fingerprint_changes(saved, dataset_fingerprint(dataset, data_options))


def check_resumable(run_dir: str | os.PathLike, dataset: Dataset,
                    data_options: dict[str, Any] | None = None) -> None:
  """Refuses to resume a run on other data than it was trained on (a resumed run would train on
  one dataset and be evaluated on the one model.json names). A run without a checkpoint, or
  whose model.json predates fingerprints, passes.

  Raises:
    InputError naming model.json and what changed.
  """
  path = Path(run_dir) / MODEL_FILE
  if not checkpoints.has_checkpoint(run_dir) or not path.is_file():
    return
  changes = data_changes(run_dir, dataset, data_options)
  if changes:
    raise InputError(f"this run was trained on other data ({'; '.join(changes)}): give the data "
                     "it was trained on to resume it, or --start_over to train afresh in this "
                     "directory (the run's own files are replaced)", path, "fingerprint")


def write_model_file(run_dir: str | os.PathLike, model: nerf_model.NerfModel,
                     dataset: Dataset, data_options: dict[str, Any] | None = None) -> None:
  """Records in the run's model.json what rebuilds its model: the scene, the capacity, the edit
  region and its view dependence, a summary of the dataset, the options it was loaded with and
  its fingerprint (`dataset_fingerprint`, which a resume checks)."""
  files.write_json(Path(run_dir) / MODEL_FILE, {
      "scene": dataclasses.asdict(model.scene),
      "capacity": dataclasses.asdict(model.capacity),
      "edit_region": model.edit_region,
      "region_view_dependence": model.region_view_dependence,
      "dataset": dataset.summary(),
      "data_options": dict(data_options or {}),
      "fingerprint": dataset_fingerprint(dataset, data_options),
  })


def read_model_file(run_dir: str | os.PathLike) -> tuple[nerf_model.NerfModel, dict[str, Any]]:
  """The model of a run and the rest of model.json (dataset summary, data options)."""
  path = Path(run_dir) / MODEL_FILE
  description = files.read_json(path)
  try:
    model = nerf_model.NerfModel(SceneInfo.from_json(description["scene"]),
                                 Capacity.from_json(description["capacity"]),
                                 description.get("edit_region"),
                                 description.get("region_view_dependence", True))
  except (KeyError, TypeError, ValueError, InputError) as error:
    raise InputError(f"malformed model description ({error})", path) from None
  return model, description


def build_model(dataset: Dataset, capacity: Capacity | None = None,
                rules: CapacityRules = CapacityRules()) -> nerf_model.NerfModel:
  """The model for a dataset: `capacity`, or the one `rules` derive from the dataset."""
  scene = SceneInfo.from_dataset(dataset)
  return nerf_model.NerfModel(scene, capacity or derive_capacity(scene, rules))


def carved_to_visual_hull(state: TrainState, dataset: Dataset, model: nerf_model.NerfModel
                          ) -> TrainState:
  """`state` with its occupancy grid's cells outside the photos' visual hull carved."""
  keep = visual_hull.hull_cells(dataset.cameras, dataset.alphas,
                                model.capacity.occupancy_resolution, model.from_unit_cube)
  grid = occupancy.carve(state.variables["occupancy"], jnp.asarray(keep))
  return state.replace(variables={**state.variables, "occupancy": grid})


def make_trainer(dataset: Dataset, *, model: nerf_model.NerfModel | None = None,
                 config: TrainConfig = TrainConfig(), init_variables=None,
                 pixel_weights=None, mesh: Mesh | None = None,
                 capacity_rules: CapacityRules = CapacityRules()) -> Trainer:
  """A Trainer at step 0 (fresh, or fine-tuning from `init_variables`), data-parallel over
  `mesh` (default: all devices); the model is derived by `capacity_rules` unless given, and
  the settings the capture chooses (`with_capture_choices`) are made here."""
  model = model or build_model(dataset, rules=capacity_rules)
  config = with_capture_choices(config, dataset, model)
  data = TrainingData.from_dataset(dataset, pixel_weights)
  if config.keypoint_depth_weight > 0:
    keypoints = keypoint_depth.triangulate(dataset.images, dataset.cameras)
    if keypoints.count:
      data = data.replace(keypoints=jax.tree.map(jnp.asarray, keypoints))
  if config.photo_consistency_weight > 0:
    data = data.replace(neighbour_views=photo_consistency.neighbour_views(
        dataset.cameras, config.photo_consistency_neighbours))
  state = init_state(model, config, init_variables)
  if config.visual_hull and can_carve(dataset, model):
    state = carved_to_visual_hull(state, dataset, model)
  return Trainer(model, config, data, state, mesh=mesh)


def train(dataset: Dataset, run_dir: str | os.PathLike, *, init_variables=None,
          steps: int | None = None, max_seconds: float | None = None, pixel_weights=None,
          model: nerf_model.NerfModel | None = None, config: TrainConfig = TrainConfig(),
          capacity_rules: CapacityRules = CapacityRules(),
          data_options: dict[str, Any] | None = None, progress: bool = True,
          replay_progress: np.ndarray | None = None) -> Trainer:
  """Trains (or resumes, if `run_dir` has a checkpoint) a NeRF on `dataset`.

  Args:
    dataset: training views.
    run_dir: where model.json and the checkpoint go.
    init_variables: start from these variables (fine-tuning; e.g. `load_run(...).variables`);
      the model must then be the one they belong to (pass `model`).
    steps, max_seconds: override TrainConfig.steps / max_seconds.
    pixel_weights: optional [N, H, W] per-pixel loss weights (multiplied with dataset.masks).
    model: the architecture (default: the run's own when resuming, else derived from the
      dataset by `capacity_rules`).
    config: training settings.
    capacity_rules: how a new model is sized (unused when `model` is given or resumed).
    data_options: how the data was loaded (root, downscale, ...), recorded for `signerf eval`.
    progress: show a progress bar.
    replay_progress: [S] float32, the schedule's progress at each of S steps (another run's
      `read_schedule`): trains exactly S steps given these, whatever the time they take.
  Returns:
    the Trainer after training (model, state, seconds_trained).
  """
  overrides = {name: value for name, value in (("steps", steps), ("max_seconds", max_seconds))
               if value is not None}
  if replay_progress is not None:
    overrides.update(steps=len(replay_progress), max_seconds=None)
  config = dataclasses.replace(config, **overrides)
  run_dir = Path(run_dir)
  ownership.check_claimable(run_dir, ownership.RUN, inputs=(("data", dataset.root),))
  if checkpoints.has_checkpoint(run_dir):
    check_resumable(run_dir, dataset, data_options)
    saved_model, _ = read_model_file(run_dir)
    if model is not None and model != saved_model:
      raise InputError("the run directory holds a different model", run_dir / MODEL_FILE)
    model = saved_model
  trainer = make_trainer(dataset, model=model, config=config, init_variables=init_variables,
                         pixel_weights=pixel_weights, capacity_rules=capacity_rules)
  trainer.replay_progress = replay_progress
  with ownership.claimed(run_dir, ownership.RUN, inputs=(("data", dataset.root),)):
    if checkpoints.has_checkpoint(run_dir):
      trainer.restore(run_dir)
    else:
      write_model_file(run_dir, trainer.model, dataset, data_options)
    trainer.run(run_dir=run_dir, progress=progress)
  return trainer
