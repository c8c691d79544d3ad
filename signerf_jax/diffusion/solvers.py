"""How each sampler family steps: DDIM, DPM-Solver++ 2M and Euler ancestral for `lax.scan`.

diffusers' schedulers are stateful objects stepping through Python loops. Here everything that
depends only on the configuration and the number of steps (timesteps, noise levels, solver
coefficients, which DPM-Solver steps are first order) is computed once on the host by
`make_schedule`, from the tables of `diffusion.schedulers`, into a `flax.struct` pytree of
per-step arrays. Inside a compiled loop a step is then a handful of elementwise operations on
values gathered at a traced `step_index`:

  schedule = make_schedule(config, num_inference_steps=20, strength=0.75)
  def body(carry, step_index):
    latents, solver_state = carry
    model_output = model(schedule.scale_model_input(latents, step_index),
                         schedule.timesteps[step_index])
    latents, solver_state = schedule.step(solver_state, step_index, model_output, latents,
                                          key=jax.random.fold_in(key, step_index))
    return (latents, solver_state), None
  carry = (latents, schedule.init_solver_state(latents))
  (latents, _), _ = jax.lax.scan(body, carry, jnp.arange(schedule.num_steps))

`step_index` counts the steps actually run (0 .. num_steps - 1), after img2img truncation.
Notation as in `diffusion.schedulers`.
"""

from __future__ import annotations

from typing import Any, Union

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from signerf_jax.diffusion import schedulers
from signerf_jax.diffusion.schedulers import SchedulerConfig
from signerf_jax.errors import InputError


# ----------------------------------------------------------------------------------------------
# Model output -> prediction of the clean sample.


def _predict_original_and_noise(model_output: jax.Array, sample: jax.Array, alpha: jax.Array,
                                sigma: jax.Array, prediction_type: str
                                ) -> tuple[jax.Array, jax.Array]:
  """(x0, epsilon) from the model output in VP form, sample = alpha * x0 + sigma * epsilon."""
  if prediction_type == "epsilon":
    return (sample - sigma * model_output) / alpha, model_output
  # "v_prediction": v = alpha * epsilon - sigma * x0.
  return alpha * sample - sigma * model_output, alpha * model_output + sigma * sample


class ScheduleBase:
  """What the schedules share: `timesteps` [S], no input scaling and no solver memory.

  Every schedule also has `init_noise_sigma`, `step(solver_state, step_index, model_output,
  sample, noise=None, key=None) -> (sample, solver_state)` and `add_noise(original, noise,
  step_index)`.
  """

  timesteps: jax.Array

  @property
  def num_steps(self) -> int:
    return self.timesteps.shape[0]

  def scale_model_input(self, sample: jax.Array, step_index) -> jax.Array:
    """The UNet input at step `step_index`."""
    del step_index
    return sample

  def init_solver_state(self, sample: jax.Array) -> Any:
    """The initial solver memory carried between steps."""
    del sample
    return ()


@struct.dataclass
class DDIMSchedule(ScheduleBase):
  """Deterministic DDIM (eta = 0).

  Attributes:
    timesteps: [S] float32, the UNet's timestep input at each step (integral values).
    alpha_cumprod: [S] float32 ᾱ at each step's timestep.
    alpha_cumprod_next: [S] float32 ᾱ each step moves to: at timestep t - T // N (diffusers'
      `prev_timestep`, also with trailing spacing), or the final ᾱ below t = 0.
    init_noise_sigma: () float32, the scale of the initial noise (1).
    prediction_type: "epsilon" or "v_prediction".
    clip_sample_range: the predicted x0 is clipped to [-range, range]; None disables clipping.
  """

  timesteps: jax.Array
  alpha_cumprod: jax.Array
  alpha_cumprod_next: jax.Array
  init_noise_sigma: jax.Array
  prediction_type: str = struct.field(pytree_node=False)
  clip_sample_range: float | None = struct.field(pytree_node=False)

  def step(self, solver_state: tuple[()], step_index, model_output: jax.Array, sample: jax.Array,
           noise: jax.Array | None = None, key: jax.Array | None = None
           ) -> tuple[jax.Array, tuple[()]]:
    """One DDIM step: x_next = sqrt(ᾱ_next) x0 + sqrt(1 - ᾱ_next) epsilon. Ignores noise/key."""
    del noise, key
    alpha_cumprod = self.alpha_cumprod[step_index]
    original, epsilon = _predict_original_and_noise(
        model_output, sample, jnp.sqrt(alpha_cumprod), jnp.sqrt(1 - alpha_cumprod),
        self.prediction_type)
    if self.clip_sample_range is not None:
      original = jnp.clip(original, -self.clip_sample_range, self.clip_sample_range)
    alpha_cumprod_next = self.alpha_cumprod_next[step_index]
    next_sample = (jnp.sqrt(alpha_cumprod_next) * original +
                   jnp.sqrt(1 - alpha_cumprod_next) * epsilon)
    return next_sample.astype(sample.dtype), solver_state

  def add_noise(self, original: jax.Array, noise: jax.Array, step_index) -> jax.Array:
    """The forward process at the noise level step `step_index` starts from."""
    alpha_cumprod = self.alpha_cumprod[step_index]
    return jnp.sqrt(alpha_cumprod) * original + jnp.sqrt(1 - alpha_cumprod) * noise


def _ddim_schedule(config: SchedulerConfig, num_inference_steps: int, first_step: int
                   ) -> DDIMSchedule:
  """The DDIM steps from `first_step` on, of a schedule of `num_inference_steps`."""
  cumulative = schedulers.alphas_cumprod(config)
  if config.timestep_spacing == "linspace":
    timesteps = np.linspace(0, config.num_train_timesteps - 1, num_inference_steps).round()[::-1]
  else:
    timesteps = schedulers.leading_or_trailing_timesteps(config, num_inference_steps)
  timesteps = timesteps.astype(np.int64)[first_step:]
  final = np.float32(1) if config.set_alpha_to_one else cumulative[0]
  next_timesteps = timesteps - config.num_train_timesteps // num_inference_steps
  alpha_next = np.where(next_timesteps >= 0, cumulative[np.maximum(next_timesteps, 0)], final)
  return DDIMSchedule(
      timesteps=jnp.asarray(timesteps, jnp.float32),
      alpha_cumprod=jnp.asarray(cumulative[timesteps]),
      alpha_cumprod_next=jnp.asarray(alpha_next, jnp.float32),
      init_noise_sigma=jnp.float32(1),
      prediction_type=config.prediction_type,
      clip_sample_range=config.clip_sample_range if config.clip_sample else None)


@struct.dataclass
class DPMSolverSchedule(ScheduleBase):
  """DPM-Solver++ (multistep, midpoint) of order 1 or 2 in data (x0) prediction.

  With lambda = log(alpha_t / sigma_t), h = lambda_next - lambda_now, h_0 = lambda_now -
  lambda_previous and r_0 = h_0 / h, one step is (Lu et al. 2022, "DPM-Solver++", eq. 8/9):
    x_next = (sigma_next / sigma_now) x - alpha_next (e^-h - 1) (D0 + D1 / 2),
    D0 = x0_now,  D1 = (x0_now - x0_previous) / r_0   (D1 = 0 for a first-order step).

  Attributes:
    timesteps: [S] float32 UNet timestep inputs (integral values).
    sigmas: [S + 1] float32 VE noise levels; the last is the level after the final step.
    alpha_t, sigma_t: [S] float32 VP scales at each step (for x0 and add_noise).
    sample_scale: [S] float32 sigma_next / sigma_now.
    x0_scale: [S] float32 alpha_next (e^-h - 1).
    derivative_scale: [S] float32 1 / r_0 for second-order steps, 0 for first-order ones (the
      first step run, the last step under `lower_order_final`/`euler_at_final`/zero final sigma).
    init_noise_sigma: () float32 (1).
    prediction_type: "epsilon" or "v_prediction".
  """

  timesteps: jax.Array
  sigmas: jax.Array
  alpha_t: jax.Array
  sigma_t: jax.Array
  sample_scale: jax.Array
  x0_scale: jax.Array
  derivative_scale: jax.Array
  init_noise_sigma: jax.Array
  prediction_type: str = struct.field(pytree_node=False)

  def init_solver_state(self, sample: jax.Array) -> jax.Array:
    """The previous step's x0 prediction (unused by the first, first-order step)."""
    return jnp.zeros_like(sample)

  def step(self, solver_state: jax.Array, step_index, model_output: jax.Array, sample: jax.Array,
           noise: jax.Array | None = None, key: jax.Array | None = None
           ) -> tuple[jax.Array, jax.Array]:
    """One multistep update; `solver_state` carries x0 of the previous step. Ignores noise/key."""
    del noise, key
    original, _ = _predict_original_and_noise(model_output, sample, self.alpha_t[step_index],
                                              self.sigma_t[step_index], self.prediction_type)
    x0_scale = self.x0_scale[step_index]
    derivative = self.derivative_scale[step_index] * (original - solver_state)
    next_sample = (self.sample_scale[step_index] * sample - x0_scale * original -
                   (0.5 * x0_scale) * derivative)
    return next_sample.astype(sample.dtype), original

  def add_noise(self, original: jax.Array, noise: jax.Array, step_index) -> jax.Array:
    """The forward process at the noise level step `step_index` starts from."""
    return self.alpha_t[step_index] * original + self.sigma_t[step_index] * noise


def _dpm_solver_levels(config: SchedulerConfig, num_inference_steps: int
                       ) -> tuple[np.ndarray, np.ndarray]:
  """The full DPM-Solver++ schedule as diffusers' `set_timesteps` spaces it: timesteps [N]
  int64 and noise levels [N + 1] float32 (the last: the level after the final step)."""
  cumulative = schedulers.alphas_cumprod(config)
  total = config.num_train_timesteps
  log_snr = np.log(np.sqrt(cumulative)) - np.log(np.sqrt(1 - cumulative))
  last_timestep = total - int(np.searchsorted(log_snr[::-1], config.lambda_min_clipped))
  count = num_inference_steps
  if config.timestep_spacing == "linspace":
    timesteps = np.linspace(0, last_timestep - 1, count + 1).round()[::-1][:-1]
  elif config.timestep_spacing == "leading":
    timesteps = (np.arange(count + 1) * (last_timestep // (count + 1))).round()[::-1][:-1]
    timesteps = timesteps + config.steps_offset
  else:
    timesteps = np.arange(last_timestep, 0, -total / count).round() - 1
  train_sigmas = schedulers.ve_sigmas(cumulative)
  if config.use_karras_sigmas:  # Between the extreme training noise levels.
    sigmas = schedulers.karras_sigmas(float(train_sigmas[0]), float(train_sigmas[-1]), count)
    timesteps = schedulers.sigma_to_timestep(sigmas, np.log(train_sigmas)).round()
  else:
    sigmas = np.interp(timesteps, np.arange(total), train_sigmas)
  final_sigma = train_sigmas[0] if config.final_sigmas_type == "sigma_min" else 0.0
  return (timesteps.astype(np.int64),
          np.concatenate([sigmas, [final_sigma]]).astype(np.float32))


def _dpm_solver_schedule(config: SchedulerConfig, num_inference_steps: int, first_step: int
                         ) -> DPMSolverSchedule:
  """The DPM-Solver++ steps from `first_step` on (the first of them first order)."""
  timesteps, sigmas = _dpm_solver_levels(config, num_inference_steps)
  count = len(timesteps)

  # Per-step coefficients over the full schedule, in float32 as the reference evaluates them.
  alpha, sigma = schedulers.vp_scales(sigmas)
  with np.errstate(divide="ignore", invalid="ignore"):  # sigma = 0 after the last step.
    log_snr = np.log(alpha) - np.log(sigma)
    step_size = log_snr[1:] - log_snr[:-1]  # h at steps 0 .. count - 1.
    previous_step_size = np.concatenate([[np.nan], step_size[:-1]]).astype(np.float32)
    sample_scale = sigma[1:] / sigma[:-1]
    x0_scale = alpha[1:] * (np.exp(-step_size) - np.float32(1))
    inverse_ratio = np.float32(1) / (previous_step_size / step_size)
  index = np.arange(count)
  final_first_order = (config.euler_at_final or config.final_sigmas_type == "zero" or
                       (config.lower_order_final and count < 15))
  first_order = ((config.solver_order == 1) | (index == first_step) |
                 ((index == count - 1) & final_first_order))
  derivative_scale = np.where(first_order, np.float32(0), inverse_ratio)
  run = slice(first_step, None)
  return DPMSolverSchedule(
      timesteps=jnp.asarray(timesteps[run], jnp.float32),
      sigmas=jnp.asarray(sigmas[run]),
      alpha_t=jnp.asarray(alpha[:-1][run]),
      sigma_t=jnp.asarray(sigma[:-1][run]),
      sample_scale=jnp.asarray(sample_scale[run]),
      x0_scale=jnp.asarray(x0_scale[run]),
      derivative_scale=jnp.asarray(derivative_scale[run], jnp.float32),
      init_noise_sigma=jnp.float32(1),
      prediction_type=config.prediction_type)


@struct.dataclass
class EulerAncestralSchedule(ScheduleBase):
  """Euler ancestral sampling in the VE parametrisation x = x0 + sigma * noise.

  Each step goes down to sigma_down with an Euler step of the probability-flow ODE, then adds
  fresh noise of scale sigma_up, where sigma_up² + sigma_down² = sigma_next² (Karras et al.).

  Attributes:
    timesteps: [S] float32 UNet timestep inputs (fractional with "linspace" spacing).
    sigmas: [S + 1] float32 noise levels; the last is 0.
    sigma_up, sigma_down: [S] float32.
    init_noise_sigma: () float32, the standard deviation of the initial latents.
    prediction_type: "epsilon" or "v_prediction".
  """

  timesteps: jax.Array
  sigmas: jax.Array
  sigma_up: jax.Array
  sigma_down: jax.Array
  init_noise_sigma: jax.Array
  prediction_type: str = struct.field(pytree_node=False)

  def scale_model_input(self, sample: jax.Array, step_index) -> jax.Array:
    """The UNet sees the VP-scaled sample x / sqrt(sigma² + 1)."""
    sigma = self.sigmas[step_index]
    return sample / jnp.sqrt(sigma * sigma + 1)

  def step(self, solver_state: tuple[()], step_index, model_output: jax.Array, sample: jax.Array,
           noise: jax.Array | None = None, key: jax.Array | None = None
           ) -> tuple[jax.Array, tuple[()]]:
    """One ancestral step; the fresh noise is `noise`, or drawn from `key` when noise is None."""
    if noise is None:
      if key is None:
        raise ValueError("Euler ancestral sampling needs `noise` or a PRNG `key`")
      noise = jax.random.normal(key, sample.shape, sample.dtype)
    sigma = self.sigmas[step_index]
    if self.prediction_type == "epsilon":
      original = sample - sigma * model_output
    else:  # "v_prediction", converted from the VP-scaled input the model saw.
      original = (model_output * (-sigma / jnp.sqrt(sigma * sigma + 1)) +
                  sample / (sigma * sigma + 1))
    derivative = (sample - original) / sigma
    next_sample = (sample + derivative * (self.sigma_down[step_index] - sigma) +
                   noise * self.sigma_up[step_index])
    return next_sample.astype(sample.dtype), solver_state

  def add_noise(self, original: jax.Array, noise: jax.Array, step_index) -> jax.Array:
    """The forward process at the noise level step `step_index` starts from."""
    return original + noise * self.sigmas[step_index]


def _euler_ancestral_schedule(config: SchedulerConfig, num_inference_steps: int,
                              first_step: int) -> EulerAncestralSchedule:
  """The Euler ancestral steps from `first_step` on, of a schedule of `num_inference_steps`."""
  if config.timestep_spacing == "linspace":
    timesteps = np.linspace(0, config.num_train_timesteps - 1, num_inference_steps,
                            dtype=np.float32)[::-1]
  else:
    timesteps = schedulers.leading_or_trailing_timesteps(config, num_inference_steps)
  timesteps = timesteps.astype(np.float32)
  train_sigmas = schedulers.ve_sigmas(schedulers.alphas_cumprod(config))
  sigmas = np.interp(timesteps, np.arange(len(train_sigmas)), train_sigmas)
  sigmas = np.concatenate([sigmas, [0.0]]).astype(np.float32)
  sigma_from, sigma_to = sigmas[:-1], sigmas[1:]
  sigma_up = np.sqrt(sigma_to**2 * (sigma_from**2 - sigma_to**2) / sigma_from**2)
  sigma_down = np.sqrt(sigma_to**2 - sigma_up**2)
  init_noise_sigma = sigmas.max()
  if config.timestep_spacing == "leading":
    init_noise_sigma = np.sqrt(init_noise_sigma**2 + np.float32(1))
  run = slice(first_step, None)
  return EulerAncestralSchedule(
      timesteps=jnp.asarray(timesteps[run]),
      sigmas=jnp.asarray(sigmas[run]),
      sigma_up=jnp.asarray(sigma_up[run]),
      sigma_down=jnp.asarray(sigma_down[run]),
      init_noise_sigma=jnp.asarray(init_noise_sigma, jnp.float32),
      prediction_type=config.prediction_type)


Schedule = Union[DDIMSchedule, DPMSolverSchedule, EulerAncestralSchedule]
_SCHEDULE_BUILDERS = {
    "ddim": _ddim_schedule,
    "dpm_solver_multistep": _dpm_solver_schedule,
    "euler_ancestral": _euler_ancestral_schedule,
}


def _check_step_count(config: SchedulerConfig, num_inference_steps: int) -> None:
  """Raises InputError unless 1 <= num_inference_steps <= the training timesteps."""
  if not 1 <= num_inference_steps <= config.num_train_timesteps:
    raise InputError(f"num_inference_steps must be in [1, {config.num_train_timesteps}], got "
                     f"{num_inference_steps}", field="num_inference_steps")


def make_schedule(config: SchedulerConfig, num_inference_steps: int, strength: float = 1.0
                  ) -> Schedule:
  """The per-step arrays of a sampling run (diffusers' `set_timesteps` + img2img truncation).

  Args:
    config: the scheduler configuration.
    num_inference_steps: N, the steps of the full (strength 1) schedule.
    strength: img2img / inpainting strength in (0, 1]: only the last int(N * strength) steps run
      (`schedulers.first_step_for_strength`); the image is noised with `schedule.add_noise(..., 0)`.

  Returns:
    A schedule pytree; pass it through `jit`/`scan` as an argument.
  """
  _check_step_count(config, num_inference_steps)
  first_step = schedulers.first_step_for_strength(num_inference_steps, strength)
  return _SCHEDULE_BUILDERS[config.kind](config, num_inference_steps, first_step)
