"""Training the default model: losses, train steps, learning-rate schedules and checkpoints.

Three stages, run in order, each with its own `TrainState`:
  "vae"         the AutoencoderKL on 64-pixel views: L1 + L2 reconstruction (object pixels
                can be weighted up: they fill a few percent of a view, yet their colour is what
                a prompt asks for), an L1 on image gradients (edges; no pretrained perceptual
                network exists here) and a small KL term towards N(0, 1). Afterwards its
                latents' standard deviation sets the scaling factor that brings them to unit
                variance.
  "unet"        the 9-channel inpainting UNet, the text encoder and (with `joint_controlnet`)
                the ControlNet together, on latents of the frozen VAE: noisy latents + mask
                (downsampled as diffusers does) + masked-image latents, diffusers' conventions
                (masked image = image in [-1, 1] with the masked pixels 0); loss on the
                scheduler's prediction type (epsilon or v), optionally Min-SNR-gamma weighted
                (Hang et al. 2023), with more weight on masked latents. Each sample gets the
                ControlNet at scale 1, or at scale 0 with probability `control_dropout`, so
                the UNet alone stays a complete model (scale 0 ignores the depth) and the
                ControlNet learns what depth adds (scale 1 follows it). Trained this way, by
                2,600 steps the ControlNet lowered the masked selection-region v-loss by 14-22%;
                added afterwards to a frozen UNet through its zero convolutions, it had not
                moved the loss after 1,300 steps (the shipped model's first recipe).
  "controlnet"  optional: the ControlNet alone on the normalised control depth, everything else
                frozen (ControlNet training as its paper does it, e.g. for a new control).

Determinism and resuming: a step's batch comes from `training_data.step_rng(seed, stage, step)`
and its random numbers from `fold_in(key(seed), step)`, so a step does the same work whenever
it runs. A checkpoint (`save_checkpoint`) is the whole `TrainState` -- step, parameters, their
moving average, optimizer state and every metric so far -- serialised with flax (msgpack, no
pickle) and written atomically; a resumed run is the uninterrupted one.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import time
from pathlib import Path
from typing import Any, Callable

import flax.serialization
import gin
import jax
import jax.numpy as jnp
import numpy as np
import optax
import tqdm
from flax import struct

from signerf_jax import files
from signerf_jax.clip import text as clip_text
from signerf_jax.default_model import model as model_lib
from signerf_jax.diffusion import schedulers
from signerf_jax.errors import InputError

CHECKPOINT_NAME = "checkpoint.msgpack"
Params = Any
LossFunction = Callable[[Params, Params, Any, jax.Array], tuple[jax.Array, dict[str, jax.Array]]]


@dataclasses.dataclass(frozen=True)
class StageSettings:
  """What every stage sets (gin: `<stage>_stage.<field>`).

  Attributes:
    num_steps: optimizer steps of the stage; may be raised between runs to train on from a
      checkpoint (the learning-rate schedule then stretches to the new end).
    learning_rate: peak learning rate (AdamW), reached after `warmup_steps` linear steps, then
      cosine decay to `final_learning_rate_fraction` of it at `num_steps`.
    weight_decay: AdamW's decoupled weight decay.
    gradient_clip_norm: global gradient norm clip.
    ema_decay: decay of the parameters' exponential moving average (the exported weights);
      ramped up as min(ema_decay, (1 + step) / (10 + step)); 0 keeps the raw parameters.
    seed: seeds the stage's batches and noise.
  """

  num_steps: int = 1000
  learning_rate: float = 1e-3
  warmup_steps: int = 100
  final_learning_rate_fraction: float = 0.1
  weight_decay: float = 0.0
  gradient_clip_norm: float = 1.0
  ema_decay: float = 0.0
  seed: int = 0

  def optimizer(self) -> optax.GradientTransformation:
    schedule = optax.warmup_cosine_decay_schedule(
        0.0, self.learning_rate, max(self.warmup_steps, 1),
        max(self.num_steps, self.warmup_steps + 1),
        self.learning_rate * self.final_learning_rate_fraction)
    return optax.chain(optax.clip_by_global_norm(self.gradient_clip_norm),
                       optax.adamw(schedule, weight_decay=self.weight_decay))


@gin.configurable("vae_stage")
@dataclasses.dataclass(frozen=True)
class VaeStage(StageSettings):
  """The VAE stage.

  Attributes:
    batch_size: views per step.
    masked_fraction: share of views greyed out under an inpainting mask.
    kl_weight: weight of the mean per-element KL divergence.
    gradient_weight: weight of the L1 between image gradients.
    object_weight: weight of object pixels in the L1 and L2 reconstruction terms (others: 1).
    scaling_views: views whose latents set the scaling factor.
  """

  num_steps: int = 2000
  learning_rate: float = 1e-3
  batch_size: int = 32
  masked_fraction: float = 0.3
  kl_weight: float = 1e-4
  gradient_weight: float = 1.0
  object_weight: float = 1.0
  scaling_views: int = 512


@dataclasses.dataclass(frozen=True)
class DiffusionStage(StageSettings):
  """What the UNet and ControlNet stages share.

  Attributes:
    sheets_per_batch, singles_per_batch: samples of each kind per step.
    mask_kind_weights: sampling weights of `batches.mask_kinds` (silhouette, dilated_<r> for
      each radius, box).
    sheet_mode_weights: sampling weights of `batches.SHEET_MODES`.
    caption_dropout: probability of the empty prompt (classifier-free guidance).
    min_snr_gamma: Min-SNR-gamma loss weighting; 0 disables it.
    masked_loss_weight: weight of masked latent cells relative to the rest.
    masked_ground_loss_weight: further factor on the masked cells that hold no object pixel (the
      ground and background the model repaints around the object). A hazy repaint of them is
      what a difference from the original view counts as object.
    control_dropout: probability that a sample's ControlNet scale is 0 instead of 1.
  """

  sheets_per_batch: int = 6
  singles_per_batch: int = 12
  mask_kind_weights: tuple[float, ...] = (0.1, 0.1, 0.15, 0.25, 0.4)
  sheet_mode_weights: tuple[float, float, float] = (0.3, 0.35, 0.35)
  caption_dropout: float = 0.1
  min_snr_gamma: float = 5.0
  masked_loss_weight: float = 2.0
  masked_ground_loss_weight: float = 1.0
  control_dropout: float = 0.0
  ema_decay: float = 0.999


@gin.configurable("unet_stage")
@dataclasses.dataclass(frozen=True)
class UNetStage(DiffusionStage):
  """The UNet stage; `joint_controlnet` trains the ControlNet in it too (module docstring)."""

  num_steps: int = 4000
  joint_controlnet: bool = True
  control_dropout: float = 0.25
  learning_rate: float = 3e-4
  warmup_steps: int = 200


@gin.configurable("controlnet_stage")
@dataclasses.dataclass(frozen=True)
class ControlNetStage(DiffusionStage):
  num_steps: int = 1500
  learning_rate: float = 3e-4
  warmup_steps: int = 100
  mask_kind_weights: tuple[float, ...] = (0.05, 0.05, 0.1, 0.3, 0.5)


@struct.dataclass
class TrainState:
  """Everything a stage's training carries from step to step (and checkpoints).

  Attributes:
    step: () int32, steps done.
    params: the trained parameters.
    ema_params: their exponential moving average.
    opt_state: the optimizer state.
    history: {metric: [num_steps] float32}, each step's value (NaN for steps not run yet).
    wall_seconds: () float32, training time up to this state (counted at checkpoints).
  """

  step: jax.Array
  params: Params
  ema_params: Params
  opt_state: Any
  history: dict[str, jax.Array]
  wall_seconds: jax.Array


def init_state(params: Params, settings: StageSettings, metric_names) -> TrainState:
  # Copies: the train step donates both trees, which must share no buffer with each other or
  # with the caller's arrays.
  return TrainState(step=jnp.zeros((), jnp.int32), params=jax.tree.map(jnp.array, params),
                    ema_params=jax.tree.map(jnp.array, params),
                    opt_state=settings.optimizer().init(params),
                    history={name: jnp.full((settings.num_steps,), jnp.nan, jnp.float32)
                             for name in metric_names},
                    wall_seconds=jnp.zeros((), jnp.float32))


@functools.lru_cache(maxsize=4)
def make_train_step(loss_fn: LossFunction, settings: StageSettings):
  """A compiled `(state, frozen, batch) -> state` step of `loss_fn(params, frozen, batch, key)`.

  Cached, so runs of a stage with the same loss function and settings share one compilation.
  """
  optimizer = settings.optimizer()
  base_key = jax.random.key(settings.seed)

  def train_step(state: TrainState, frozen: Params, batch: Any) -> TrainState:
    key = jax.random.fold_in(base_key, state.step)
    (loss, metrics), gradients = jax.value_and_grad(loss_fn, has_aux=True)(
        state.params, frozen, batch, key)
    updates, opt_state = optimizer.update(gradients, state.opt_state, state.params)
    params = optax.apply_updates(state.params, updates)
    step = state.step.astype(jnp.float32)
    decay = jnp.minimum(settings.ema_decay, (1.0 + step) / (10.0 + step))
    ema_params = jax.tree.map(lambda average, new: decay * average + (1.0 - decay) * new,
                              state.ema_params, params)
    metrics = {**metrics, "loss": loss, "gradient_norm": optax.tree.norm(gradients)}
    history = {name: values.at[state.step].set(metrics[name])
               for name, values in state.history.items()}
    return state.replace(step=state.step + 1, params=params, ema_params=ema_params,
                         opt_state=opt_state, history=history)

  return jax.jit(train_step, donate_argnums=0)


# ----------------------------------------------------------------------------------------------
# Losses.


def image_gradient_l1(prediction: jax.Array, target: jax.Array) -> jax.Array:
  """Mean L1 between the horizontal and vertical finite differences of [B, H, W, C] images."""
  differences = lambda x, axis: jnp.diff(x, axis=axis)
  return (jnp.mean(jnp.abs(differences(prediction, 1) - differences(target, 1)))
          + jnp.mean(jnp.abs(differences(prediction, 2) - differences(target, 2))))


def vae_loss_fn(components: model_lib.Components, settings: VaeStage) -> LossFunction:
  """loss(params, frozen (unused), `training_data.vae_batch` dict, key); metrics unweighted."""
  vae = components.vae

  def loss_fn(params, frozen, batch, key):
    del frozen
    target = 2.0 * batch["image"] - 1.0
    pixel_weights = 1.0 + (settings.object_weight - 1.0) * batch["object"]
    weighted_mean = lambda values: jnp.sum(pixel_weights * values) / (
        jnp.sum(pixel_weights) * values.shape[-1])
    posterior = vae.apply({"params": params}, target, method=vae.encode)
    reconstruction = vae.apply({"params": params}, posterior.sample(key), method=vae.decode)
    error = reconstruction - target
    kl = 0.5 * jnp.mean(jnp.square(posterior.mean) + jnp.exp(posterior.logvar) - 1.0
                        - posterior.logvar)
    metrics = {"l1": jnp.mean(jnp.abs(error)), "l2": jnp.mean(jnp.square(error)),
               "gradient_l1": image_gradient_l1(reconstruction, target), "kl": kl}
    loss = (weighted_mean(jnp.abs(error)) + weighted_mean(jnp.square(error))
            + settings.gradient_weight * metrics["gradient_l1"] + settings.kl_weight * kl)
    return loss, metrics

  return loss_fn


VAE_METRICS = ("loss", "gradient_norm", "l1", "l2", "gradient_l1", "kl")
DIFFUSION_METRICS = ("loss", "gradient_norm", "loss_sheets", "loss_singles")


def encode_latents(components: model_lib.Components, vae_params: Params, images: jax.Array,
                   key: jax.Array) -> jax.Array:
  """[B, H, W, 3] images in [-1, 1] -> [B, H/f, W/f, C] diffusion latents (posterior samples)."""
  vae = components.vae
  posterior = vae.apply({"params": vae_params}, images, method=vae.encode)
  return vae.config.to_diffusion_latents(posterior.sample(key))


def inpainting_conditioning(components: model_lib.Components, vae_params: Params,
                            image: jax.Array, mask: jax.Array, key: jax.Array):
  """The clean latents and the UNet's extra channels, as diffusers' inpainting pipelines make them.

  Args:
    image: [B, H, W, 3] in [0, 1]; mask: [B, H, W, 1] in [0, 1] (binarised at 0.5).
  Returns:
    latents [B, h, w, C]; mask [B, h, w, 1] (nearest: every f-th pixel, as torch's interpolate);
    masked-image latents [B, h, w, C] (the image in [-1, 1] with masked pixels 0).
  """
  factor = 2 ** (len(components.vae.config.block_out_channels) - 1)
  image = 2.0 * image - 1.0
  keep = (mask < 0.5).astype(jnp.float32)
  latents = encode_latents(components, vae_params, jnp.concatenate([image, image * keep]), key)
  latents, masked_latents = jnp.split(jax.lax.stop_gradient(latents), 2)
  return latents, (1.0 - keep)[:, ::factor, ::factor], masked_latents


def object_cells(object_pixels: jax.Array, latent_shape: tuple[int, int]) -> jax.Array:
  """[B, h, w, 1] 1 where a latent cell's block of pixels holds any object pixel.

  Args:
    object_pixels: [B, H, W, 1] in {0, 1}, H and W multiples of h and w.
  """
  batch, height, width, _ = object_pixels.shape
  blocks = object_pixels.reshape(batch, latent_shape[0], height // latent_shape[0],
                                 latent_shape[1], width // latent_shape[1], 1)
  return blocks.max(axis=(2, 4))


def diffusion_loss_fn(components: model_lib.Components, scheduler: schedulers.SchedulerConfig,
                      settings: DiffusionStage) -> LossFunction:
  """loss(params, frozen, {"sheets": part, "singles": part}, key) of the UNet or ControlNet stage.

  params: the trained parts of {"unet", "text_encoder", "controlnet"}; frozen: the others and
  "vae". The ControlNet takes part when either holds it, at a per-sample scale of 1 or (with
  probability `settings.control_dropout`) 0. A part is `training_data.diffusion_batch`'s dict;
  the loss is the mean over all samples of both parts.
  """
  alphas_cumprod = jnp.asarray(schedulers.alphas_cumprod(scheduler))
  text_module = clip_text.CLIPTextTransformer(components.text)

  def part_losses(weights, part, key):
    noise_key, time_key, latent_key, dropout_key = jax.random.split(key, 4)
    latents, mask, masked_latents = inpainting_conditioning(
        components, weights["vae"], part["image"], part["mask"], latent_key)
    batch = latents.shape[0]
    context = text_module.apply({"params": weights["text_encoder"]}, part["ids"]).last_hidden_state
    timesteps = jax.random.randint(time_key, (batch,), 0, scheduler.num_train_timesteps)
    noise = jax.random.normal(noise_key, latents.shape)
    alpha_cumprod = alphas_cumprod[timesteps][:, None, None, None]
    alpha, sigma = jnp.sqrt(alpha_cumprod), jnp.sqrt(1.0 - alpha_cumprod)
    noisy = alpha * latents + sigma * noise
    control = None
    if "controlnet" in weights:
      control_image = jnp.repeat(part["control"], model_lib.CONTROL_CHANNELS, axis=-1)
      control = components.controlnet.apply({"params": weights["controlnet"]}, noisy, timesteps,
                                            context, control_image, 1.0)
      kept = jax.random.bernoulli(dropout_key, 1.0 - settings.control_dropout, (batch, 1, 1, 1))
      control = jax.tree.map(lambda residual: residual * kept, control)
    prediction = components.unet.apply(
        {"params": weights["unet"]}, jnp.concatenate([noisy, mask, masked_latents], -1),
        timesteps, context, control=control)
    if scheduler.prediction_type == "v_prediction":
      target = alpha * noise - sigma * latents
    else:
      target = noise
    masked_ground = mask * (1.0 - object_cells(part["object"], mask.shape[1:3]))
    cell_weights = ((1.0 + (settings.masked_loss_weight - 1.0) * mask)
                    * (1.0 + (settings.masked_ground_loss_weight - 1.0) * masked_ground))
    squared = jnp.sum(cell_weights * jnp.square(prediction - target), axis=(1, 2, 3))
    per_sample = squared / (jnp.sum(cell_weights, axis=(1, 2, 3)) * latents.shape[-1])
    if settings.min_snr_gamma > 0:
      snr = alpha_cumprod[:, 0, 0, 0] / (1.0 - alpha_cumprod[:, 0, 0, 0])
      clipped = jnp.minimum(snr, settings.min_snr_gamma)
      per_sample = per_sample * (clipped / (snr + 1.0) if scheduler.prediction_type ==
                                 "v_prediction" else clipped / snr)
    return per_sample

  def loss_fn(params, frozen, batch, key):
    weights = {**frozen, **params}
    losses = {kind: part_losses(weights, batch[kind], jax.random.fold_in(key, index))
              for index, kind in enumerate(("sheets", "singles"))}
    total = jnp.concatenate([losses["sheets"], losses["singles"]]).mean()
    return total, {"loss_sheets": losses["sheets"].mean(),
                   "loss_singles": losses["singles"].mean()}

  return loss_fn


# ----------------------------------------------------------------------------------------------
# Checkpoints and the stage loop.


def save_checkpoint(path: str | os.PathLike, state: TrainState) -> None:
  """Writes the whole state atomically (msgpack via flax.serialization)."""
  files.write_bytes(path, flax.serialization.to_bytes(jax.device_get(state)))


def restore_checkpoint(path: str | os.PathLike, template: TrainState) -> TrainState:
  """The state saved at `path`, in the structure of `template` (a fresh `init_state`)."""
  path = Path(path)
  try:
    restored = flax.serialization.from_bytes(template, path.read_bytes())
  except (OSError, ValueError, KeyError, TypeError) as error:
    raise InputError(f"not a checkpoint of this stage and configuration ({error})", path) from None
  shapes = lambda tree: jax.tree.map(np.shape, tree)
  if (not isinstance(restored.history, dict) or set(restored.history) != set(template.history)
      or shapes(restored.replace(history={})) != shapes(template.replace(history={}))):
    raise InputError("checkpoint shapes differ from this configuration's", path)
  # The stage's num_steps may have changed since: raised, the history gets NaN for the new steps
  # and training extends from the checkpoint; lowered, the steps done keep their metrics (the
  # stage counts as finished).
  length = max(template.history["loss"].shape[0], int(restored.step))
  restored = restored.replace(history={
      name: np.concatenate([np.asarray(values)[:length],
                            np.full(max(length - len(values), 0), np.nan, np.float32)])
      for name, values in restored.history.items()})
  return jax.tree.map(jnp.asarray, restored)


def stage_finished(directory: str | os.PathLike, settings: StageSettings) -> bool:
  """Whether `directory` holds a checkpoint of all `settings.num_steps` steps (read cheaply)."""
  path = Path(directory) / CHECKPOINT_NAME
  if not path.is_file():
    return False
  state = flax.serialization.msgpack_restore(path.read_bytes())
  return int(state["step"]) >= settings.num_steps


@dataclasses.dataclass(frozen=True)
class RunBudget:
  """When a run stops (then it checkpoints and returns; a later run resumes).

  Attributes:
    deadline: `time.monotonic()` value after which no new step starts.
    max_steps: most steps a stage runs in this run (None: no limit).
    checkpoint_seconds: wall time between checkpoints.
    progress: show progress bars.
  """

  deadline: float = float("inf")
  max_steps: int | None = None
  checkpoint_seconds: float = 300.0
  progress: bool = True


def run_stage(name: str, directory: str | os.PathLike, settings: StageSettings,
              initial_params: Callable[[], Params], frozen: Params, loss_fn: LossFunction,
              make_batch: Callable[[int], Any], metric_names, budget: RunBudget) -> TrainState:
  """Trains one stage from its checkpoint in `directory` (or from scratch) until it is finished
  or the budget's deadline passes; checkpoints along the way and at the end.

  Args:
    name: the stage's name (progress bar).
    initial_params: builds the starting parameters (called only without a checkpoint).
    make_batch: step -> that step's batch.
    metric_names: what the loss function reports (plus "loss" and "gradient_norm").
  Returns:
    The state reached (`int(state.step) == settings.num_steps` when finished).
  """
  path = Path(directory) / CHECKPOINT_NAME
  template = init_state(initial_params(), settings, metric_names)
  state = restore_checkpoint(path, template) if path.is_file() else template
  train_step = make_train_step(loss_fn, settings)
  step = first_step = int(state.step)
  bar = tqdm.tqdm(total=settings.num_steps, initial=step, desc=f"training {name}", unit="step",
                  disable=not budget.progress)
  last_save = time.monotonic()

  def checkpoint(state):
    nonlocal last_save
    now = time.monotonic()
    state = state.replace(wall_seconds=state.wall_seconds + (now - last_save))
    save_checkpoint(path, state)
    last_save = now
    return state

  last_step = settings.num_steps if budget.max_steps is None else min(
      settings.num_steps, first_step + budget.max_steps)
  while step < last_step and time.monotonic() < budget.deadline:
    state = train_step(state, frozen, make_batch(step))
    step += 1
    bar.update()
    if step % 10 == 0 or step == settings.num_steps:
      bar.set_postfix(loss=f"{float(state.history['loss'][step - 1]):.4f}")
    if time.monotonic() - last_save >= budget.checkpoint_seconds:
      state = checkpoint(state)
  bar.close()
  if step > first_step:
    state = checkpoint(state)
  return state
