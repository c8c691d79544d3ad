"""The default model's three training stages wired together, resumable across runs.

    run = stages.train(run_directory, data, architecture, budget)

Each stage trains in `<run_directory>/<stage>/` (its checkpoint, `checkpoints.CHECKPOINT_NAME`)
and is skipped once it has done all its steps; a run stops starting new steps at the budget's
deadline, so training spans as many runs as it needs. What each stage trains and freezes:

  stage        trains                            frozen                   parameters used later
  vae          AutoencoderKL                     -                        raw (no averaging)
  unet         UNet + text encoder (+ ControlNet  VAE                      moving average
               with `unet_stage.joint_controlnet`)
  controlnet   ControlNet (optional refinement)  VAE, UNet, text encoder  moving average

Between the VAE and the UNet stage the VAE's latent scaling factor is measured (1 / std of the
latents of a fixed set of training views), so the diffusion model sees unit-variance latents;
it is part of the exported VAE config.

A run can also start every stage from an exported model (`initial`, e.g. the shipped weights)
instead of random parameters: how training continues on a machine that has the weights but not
the run's checkpoints (give the stages to skip zero steps).
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any, Callable

import gin
import jax
import jax.numpy as jnp
import numpy as np
from flax import traverse_util

from signerf_jax.default_model import losses
from signerf_jax.default_model import model as model_lib
from signerf_jax.default_model import stage_settings
from signerf_jax.default_model import training
from signerf_jax.default_model import training_data
from signerf_jax.diffusion import schedulers
from signerf_jax.errors import InputError

STAGES = ("vae", "unet", "controlnet")
SCALING_SEED = 12345  # The views that set the latent scaling factor (fixed, not the run's seed).


@gin.configurable("default_model_training")
@dataclasses.dataclass(frozen=True)
class TrainingPlan:
  """The stages' settings (each gin-configurable on its own: `vae_stage`, `unet_stage`, ...).

  Attributes:
    seed: initialises every stage's parameters (stage settings carry their own batch seeds).
  """

  seed: int = 0
  vae: stage_settings.VaeStage = dataclasses.field(default_factory=stage_settings.VaeStage)
  unet: stage_settings.UNetStage = dataclasses.field(default_factory=stage_settings.UNetStage)
  controlnet: stage_settings.ControlNetStage = dataclasses.field(
      default_factory=stage_settings.ControlNetStage)


@dataclasses.dataclass(frozen=True)
class TrainedModel:
  """Where training stands and the parameters to export.

  Attributes:
    architecture: with the measured VAE scaling factor once the VAE stage is done.
    steps: {stage: steps done}; finished: {stage: whether all steps are done}.
    params: {"vae", "unet", "text_encoder", "controlnet"}: the parameters reached so far (the
      ControlNet's initialisation, which adds nothing, before its stage starts); None for the
      components whose stage has not started.
    histories: {stage: {metric: [steps done] values}}.
    wall_seconds: {stage: training time so far, over all runs}.
  """

  architecture: model_lib.Architecture
  steps: dict[str, int]
  finished: dict[str, bool]
  params: dict[str, Any]
  histories: dict[str, dict[str, np.ndarray]]
  wall_seconds: dict[str, float]

  @property
  def complete(self) -> bool:
    return all(self.finished.values())


def latent_scaling_factor(components: model_lib.Components, vae_params, data, views: int
                          ) -> float:
  """1 / std of the VAE's latent means over `views` fixed training views."""
  images = training_data.vae_batch(data, np.random.default_rng(SCALING_SEED), views,
                                   0.0)["image"]
  vae = components.vae
  encode = jax.jit(lambda images: vae.apply({"params": vae_params}, 2.0 * images - 1.0,
                                            method=vae.encode).mean)
  means = np.concatenate([np.asarray(encode(images[start:start + 32]))
                          for start in range(0, views, 32)])
  return float(1.0 / means.std())


def _stage_record(state: training.TrainState, settings: stage_settings.StageSettings) -> dict:
  """What `TrainedModel` reports of a stage: steps, finished, history and wall_seconds."""
  steps = int(state.step)
  return {"steps": steps, "finished": steps >= settings.num_steps,
          "history": {name: np.asarray(values[:steps]) for name, values in state.history.items()},
          "wall_seconds": float(state.wall_seconds)}


def _trained_model(architecture: model_lib.Architecture, params: dict[str, Any],
                   records: dict[str, dict]) -> TrainedModel:
  """The `TrainedModel` of the stages run so far ({stage: `_stage_record`})."""
  field = lambda key: {name: record[key] for name, record in records.items()}
  return TrainedModel(architecture, field("steps"), field("finished"), params, field("history"),
                      field("wall_seconds"))


@dataclasses.dataclass(frozen=True)
class _Run:
  """What every stage of one `train` call reads (`train`'s arguments), and each component's
  random number generator (seeded by the plan's seed and the component)."""

  directory: Path
  data: training_data.SplitData
  plan: TrainingPlan
  budget: training.RunBudget
  initial: dict[str, Any] | None
  rngs: dict[str, np.random.Generator]

  def start_from(self, name: str, fresh: Callable[[], Any]) -> Callable[[], Any]:
    """`fresh`, or the given initial parameters once they are checked to fit it."""
    if self.initial is None or name not in self.initial:
      return fresh
    shapes = lambda params: {path: np.shape(leaf) for path, leaf in
                             traverse_util.flatten_dict(params).items()}
    if shapes(jax.eval_shape(fresh)) != shapes(self.initial[name]):
      raise InputError(f"the initial {name} parameters do not fit the architecture",
                       field="default_model_architecture")
    return lambda: self.initial[name]

  def vae_batches(self, settings: stage_settings.VaeStage) -> Callable[[int], Any]:
    """step -> that step's `training_data.vae_batch` of the VAE stage."""
    return lambda step: training_data.vae_batch(
        self.data, training_data.step_rng(settings.seed, "vae", step), settings.batch_size,
        settings.masked_fraction)

  def diffusion_batches(self, settings: stage_settings.DiffusionStage, stage: str
                        ) -> Callable[[int], Any]:
    """step -> that step's `training_data.diffusion_batch` of the UNet or ControlNet stage."""
    return lambda step: jax.tree.map(jnp.asarray, training_data.diffusion_batch(
        self.data, training_data.step_rng(settings.seed, stage, step), settings.sheets_per_batch,
        settings.singles_per_batch, settings.mask_kind_weights, settings.sheet_mode_weights,
        settings.caption_dropout))


def _train_vae(run: _Run, components: model_lib.Components) -> training.TrainState:
  """Runs (or resumes) the VAE stage."""
  settings = run.plan.vae
  return training.run_stage(
      "vae", run.directory / "vae", settings,
      run.start_from("vae", lambda: model_lib.init_vae(components, run.rngs["vae"])),
      {}, losses.vae_loss_fn(components, settings), run.vae_batches(settings),
      losses.VAE_METRICS, run.budget)


def _train_unet(run: _Run, components: model_lib.Components,
                scheduler: schedulers.SchedulerConfig, vae_params) -> training.TrainState:
  """Runs (or resumes) the UNet stage: UNet and text encoder, with the ControlNet when
  `joint_controlnet`, on the frozen VAE."""
  settings = run.plan.unet

  def start():
    params = {
        "unet": run.start_from("unet", lambda: model_lib.init_unet(
            components, run.rngs["unet"]))(),
        "text_encoder": run.start_from("text_encoder", lambda: model_lib.init_text_encoder(
            components, run.rngs["text_encoder"]))()}
    if settings.joint_controlnet:
      params["controlnet"] = run.start_from("controlnet", lambda: model_lib.init_controlnet(
          components, params["unet"], run.rngs["controlnet"]))()
    return params

  return training.run_stage(
      "unet", run.directory / "unet", settings, start, {"vae": vae_params},
      losses.diffusion_loss_fn(components, scheduler, settings),
      run.diffusion_batches(settings, "unet"), losses.DIFFUSION_METRICS, run.budget)


def _train_controlnet(run: _Run, components: model_lib.Components,
                      scheduler: schedulers.SchedulerConfig, params: dict[str, Any]
                      ) -> training.TrainState:
  """Runs (or resumes) the ControlNet stage from `params["controlnet"]`, the others frozen."""
  settings = run.plan.controlnet
  return training.run_stage(
      "controlnet", run.directory / "controlnet", settings,
      lambda: {"controlnet": params["controlnet"]}, params,
      losses.diffusion_loss_fn(components, scheduler, settings),
      run.diffusion_batches(settings, "controlnet"), losses.DIFFUSION_METRICS, run.budget)


def train(run_directory: str | os.PathLike, data: training_data.SplitData,
          architecture: model_lib.Architecture, budget: training.RunBudget,
          plan: TrainingPlan | None = None, initial: dict[str, Any] | None = None
          ) -> TrainedModel:
  """Runs (or resumes) the stages in order until all are done or the budget's deadline.

  Args:
    run_directory: holds one folder per stage.
    data: the training split.
    architecture: the model's sizes (its vae_scaling_factor is replaced by the measured one).
    budget: deadline, checkpoint interval, progress display.
    plan: stage settings (default: the gin-bound `TrainingPlan`).
    initial: {"vae", "unet", "text_encoder", "controlnet"} or some of them: parameters the
      stages start from instead of their random initialisation (`export.initial_params` of an
      exported model), so training continues from shipped weights when the run's checkpoints
      are gone (or, given only the VAE, a new diffusion model is trained on it).
  """
  plan = TrainingPlan() if plan is None else plan
  run = _Run(Path(run_directory), data, plan, budget, initial, {
      name: np.random.default_rng([plan.seed, index])
      for index, name in enumerate(("vae", "unet", "text_encoder", "controlnet"))})
  components = model_lib.build(architecture, data.tokenizer.vocab_size)
  vae_state = _train_vae(run, components)
  records = {"vae": _stage_record(vae_state, plan.vae)}
  params = {"vae": jax.device_get(vae_state.ema_params)}
  if not records["vae"]["finished"]:
    return _trained_model(architecture, params, records)

  architecture = dataclasses.replace(architecture, vae_scaling_factor=latent_scaling_factor(
      components, params["vae"], data, plan.vae.scaling_views))
  components = model_lib.build(architecture, data.tokenizer.vocab_size)
  scheduler = schedulers.scheduler_config(architecture.scheduler_config())
  unet_state = _train_unet(run, components, scheduler, params["vae"])
  records["unet"] = _stage_record(unet_state, plan.unet)
  params.update(jax.device_get(unet_state.ema_params))
  if "controlnet" not in params:
    params["controlnet"] = run.start_from("controlnet", lambda: model_lib.init_controlnet(
        components, params["unet"], run.rngs["controlnet"]))()
  if not records["unet"]["finished"]:
    return _trained_model(architecture, params, records)

  controlnet_state = _train_controlnet(run, components, scheduler, params)
  records["controlnet"] = _stage_record(controlnet_state, plan.controlnet)
  params.update(jax.device_get(controlnet_state.ema_params))
  return _trained_model(architecture, params, records)
