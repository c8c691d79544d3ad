"""Which noise schedule: diffusers' scheduler configuration and the tables it defines.

A `SchedulerConfig` is a diffusers `scheduler_config.json` (DDIM, DPM-Solver++ multistep or Euler
ancestral), checked against what this port implements (`scheduler_config`,
`load_scheduler_config`). From it follow, on the host in numpy and in float32 with the
reference's operation order, the tables every sampler family builds on: the cumulative ᾱ_t of the
training noise schedule (`alphas_cumprod`), diffusers' timestep spacings, conversions between
noise levels and timesteps, and which steps img2img strength skips (`first_step_for_strength`).
How each family steps through these levels inside a compiled loop is `diffusion.solvers`.

Notation: alpha_cumprod = ᾱ_t; VP scales alpha_t = sqrt(ᾱ_t), sigma_t = sqrt(1 - ᾱ_t); the
sigma-based schedulers use the VE noise level sigma = sqrt((1 - ᾱ) / ᾱ) = sigma_t / alpha_t.
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from signerf_jax import files
from signerf_jax.errors import InputError

# diffusers class name -> our kind.
KINDS = {
    "DDIMScheduler": "ddim",
    "DPMSolverMultistepScheduler": "dpm_solver_multistep",
    "EulerAncestralDiscreteScheduler": "euler_ancestral",
}
COMMON_FIELDS = ("num_train_timesteps", "beta_start", "beta_end", "beta_schedule", "trained_betas",
                 "prediction_type", "timestep_spacing", "steps_offset")
# The configuration fields each diffusers class reads (others in a scheduler_config.json, e.g.
# PNDM's `skip_prk_steps`, are ignored as diffusers' `from_config` ignores them).
KIND_FIELDS = {
    "ddim": COMMON_FIELDS + ("clip_sample", "clip_sample_range", "set_alpha_to_one"),
    "dpm_solver_multistep": COMMON_FIELDS + (
        "solver_order", "lower_order_final", "euler_at_final", "use_karras_sigmas",
        "final_sigmas_type", "lambda_min_clipped"),
    "euler_ancestral": COMMON_FIELDS,
}
# The one class default that differs between the classes.
DEFAULT_SPACING = {"ddim": "leading", "dpm_solver_multistep": "linspace",
                   "euler_ancestral": "linspace"}
# Options the classes accept that are not implemented here: only these values are allowed.
# diffusers itself maps DPM-Solver's "deis" algorithm and UniPC's solver types onto these.
UNSUPPORTED_OPTIONS = {
    "ddim": {"thresholding": (False,), "rescale_betas_zero_snr": (False,)},
    "dpm_solver_multistep": {
        "thresholding": (False,), "rescale_betas_zero_snr": (False,),
        "algorithm_type": ("dpmsolver++", "deis"),
        "solver_type": ("midpoint", "logrho", "bh1", "bh2"), "variance_type": (None,),
        "use_exponential_sigmas": (False,), "use_beta_sigmas": (False,),
        "use_lu_lambdas": (False,), "use_flow_sigmas": (False,), "use_dynamic_shifting": (False,)},
    "euler_ancestral": {"rescale_betas_zero_snr": (False,)},
}
CHOICES = {
    "beta_schedule": ("linear", "scaled_linear"),
    "prediction_type": ("epsilon", "v_prediction"),
    "timestep_spacing": ("linspace", "leading", "trailing"),
    "solver_order": (1, 2),
    "final_sigmas_type": ("zero", "sigma_min"),
}


@dataclasses.dataclass(frozen=True)
class SchedulerConfig:
  """A diffusers scheduler configuration, restricted to what is implemented here.

  Field names and defaults are diffusers'; `timestep_spacing` None takes the kind's default
  ("leading" for DDIM, "linspace" for the others).
  """

  kind: str  # "ddim", "dpm_solver_multistep" or "euler_ancestral".
  num_train_timesteps: int = 1000
  beta_start: float = 0.0001
  beta_end: float = 0.02
  beta_schedule: str = "linear"
  trained_betas: tuple[float, ...] | None = None  # Overrides the beta schedule when given.
  prediction_type: str = "epsilon"
  timestep_spacing: str | None = None
  steps_offset: int = 0  # Added to "leading" timesteps (SD checkpoints use 1).
  # DDIM.
  clip_sample: bool = True
  clip_sample_range: float = 1.0
  set_alpha_to_one: bool = True  # ᾱ after the last step: 1, or ᾱ at t = 0.
  # DPM-Solver++.
  solver_order: int = 2
  lower_order_final: bool = True  # A first-order last step when there are < 15 steps.
  euler_at_final: bool = False
  use_karras_sigmas: bool = False
  final_sigmas_type: str = "zero"  # Noise level after the last step: 0 or sigma at t = 0.
  lambda_min_clipped: float = -math.inf

  def __post_init__(self):
    if self.kind not in KIND_FIELDS:
      raise InputError(f"unknown scheduler kind {self.kind!r}; expected one of "
                       f"{sorted(KIND_FIELDS)}", field="kind")
    if self.timestep_spacing is None:
      object.__setattr__(self, "timestep_spacing", DEFAULT_SPACING[self.kind])
    for field, allowed in CHOICES.items():
      if field == "beta_schedule" and self.trained_betas is not None:
        continue
      if getattr(self, field) not in allowed:
        raise InputError(f"{field}={getattr(self, field)!r} is not implemented (supported: "
                         f"{allowed})", field=field)


def scheduler_config(config: Mapping[str, Any], kind: str | None = None,
                     source: str | os.PathLike | None = None, **overrides) -> SchedulerConfig:
  """A `SchedulerConfig` from a diffusers config dict, like `<Class>.from_config(config, **kw)`.

  Args:
    config: the contents of a `scheduler_config.json`.
    kind: the scheduler to build; None takes it from `_class_name`. Choosing another kind than
      the checkpoint's (e.g. DPM-Solver++ for a PNDM config) reuses the fields that kind reads.
    source: the file named in errors.
    **overrides: fields replacing the file's values (e.g. use_karras_sigmas=True).
  """
  if kind is None:
    class_name = config.get("_class_name")
    if class_name not in KINDS:
      raise InputError(f"scheduler {class_name!r} is not implemented; choose a kind from "
                       f"{sorted(KINDS.values())}", source, "_class_name")
    kind = KINDS[class_name]
  if kind not in KIND_FIELDS:
    raise InputError(f"unknown scheduler kind {kind!r}; expected one of {sorted(KIND_FIELDS)}",
                     source, "kind")
  values = {**config, **overrides}
  for field, allowed in UNSUPPORTED_OPTIONS[kind].items():
    if values.get(field, allowed[0]) not in allowed:
      raise InputError(f"{field}={values[field]!r} is not implemented (supported: {allowed})",
                       source, field)
  unknown = sorted(set(overrides) - set(KIND_FIELDS[kind]) - set(UNSUPPORTED_OPTIONS[kind]))
  if unknown:
    raise InputError(f"{kind} has no option {unknown[0]!r}", source, unknown[0])
  fields = {name: values[name] for name in KIND_FIELDS[kind] if name in values}
  if fields.get("trained_betas") is not None:
    fields["trained_betas"] = tuple(float(beta) for beta in fields["trained_betas"])
  if fields.get("lambda_min_clipped") is not None:
    fields["lambda_min_clipped"] = float(fields["lambda_min_clipped"])
  try:
    return SchedulerConfig(kind=kind, **fields)
  except InputError as error:  # Name the file too.
    raise InputError(error.problem, source, error.field) from None


def load_scheduler_config(path: str | os.PathLike, kind: str | None = None,
                          **overrides) -> SchedulerConfig:
  """Reads `<checkpoint>/scheduler/scheduler_config.json` (a directory or the file itself)."""
  path = Path(path)
  if path.is_dir():
    path = path / "scheduler_config.json"
  config = files.read_json(path)
  return scheduler_config(config, kind, source=path, **overrides)


# ----------------------------------------------------------------------------------------------
# The tables (numpy, float32 where the reference computes in float32).


def _torch_linspace_float32(start: float, end: float, count: int) -> np.ndarray:
  """torch.linspace(start, end, count, dtype=float32), bit for bit.

  torch evaluates `start + step * i` for the first half and `end - step * (count - 1 - i)` for
  the second with a fused multiply-add (one rounding); numpy's linspace rounds differently, which
  shifts small betas by up to 1 ulp. The float64 products of float32 values are exact, so one
  float64 evaluation rounded to float32 reproduces the FMA.
  """
  start32, end32 = np.float32(start), np.float32(end)
  step = np.float64((end32 - start32) / np.float32(max(count - 1, 1)))
  index = np.arange(count)
  values = np.where(index < count // 2, np.float64(start32) + step * index,
                    np.float64(end32) - step * (count - 1 - index))
  return values.astype(np.float32)


def alphas_cumprod(config: SchedulerConfig) -> np.ndarray:
  """ᾱ_t for t = 0 .. num_train_timesteps - 1: [T] float32, as diffusers computes it."""
  count = config.num_train_timesteps
  if config.trained_betas is not None:
    betas = np.asarray(config.trained_betas, np.float32)
  elif config.beta_schedule == "linear":
    betas = _torch_linspace_float32(config.beta_start, config.beta_end, count)
  else:  # "scaled_linear": linear in sqrt(beta), Stable Diffusion's schedule.
    betas = _torch_linspace_float32(config.beta_start**0.5, config.beta_end**0.5, count)**2
  # torch's cumprod accumulates float32 in float64; so does this.
  return np.cumprod((np.float32(1) - betas).astype(np.float64)).astype(np.float32)


def first_step_for_strength(num_inference_steps: int, strength: float) -> int:
  """How many leading steps img2img skips: diffusers pipelines' `get_timesteps`.

  With strength s < 1 the image is noised to the level of step N - int(N * s) and only the
  remaining int(N * s) steps run.
  """
  if not 0.0 <= strength <= 1.0:
    raise InputError(f"strength must be in [0, 1], got {strength}", field="strength")
  start = num_inference_steps - min(int(num_inference_steps * strength), num_inference_steps)
  if start >= num_inference_steps:
    raise InputError(f"strength {strength} with {num_inference_steps} steps leaves no step to "
                     "run", field="strength")
  return max(start, 0)


def leading_or_trailing_timesteps(config: SchedulerConfig, count: int) -> np.ndarray:
  """DDIM's and Euler's "leading" or "trailing" timesteps: [count] float64 integral values."""
  total = config.num_train_timesteps
  if config.timestep_spacing == "leading":
    return (np.arange(count) * (total // count)).round()[::-1] + config.steps_offset
  # "trailing": evenly spaced, ending exactly at the last training timestep.
  return np.round(np.arange(total, 0, -total / count)) - 1


def ve_sigmas(cumulative: np.ndarray) -> np.ndarray:
  """ᾱ [T] -> the VE noise level sqrt((1 - ᾱ) / ᾱ) of each training timestep, [T] float32."""
  return np.sqrt((1 - cumulative) / cumulative)


def karras_sigmas(sigma_min: float, sigma_max: float, count: int) -> np.ndarray:
  """[count] float64 noise levels from sigma_max down to sigma_min, spaced as Karras et al. 2022
  (eq. 5, rho = 7)."""
  ramp = np.linspace(0, 1, count)
  return (sigma_max**(1 / 7) + ramp * (sigma_min**(1 / 7) - sigma_max**(1 / 7)))**7


def sigma_to_timestep(sigmas: np.ndarray, log_sigmas: np.ndarray) -> np.ndarray:
  """Fractional training timestep of each noise level, interpolating log sigma (diffusers)."""
  log_sigma = np.log(np.maximum(sigmas, 1e-10))
  distances = log_sigma - log_sigmas[:, np.newaxis]
  low = np.cumsum(distances >= 0, axis=0).argmax(axis=0).clip(max=log_sigmas.shape[0] - 2)
  weight = np.clip((log_sigmas[low] - log_sigma) / (log_sigmas[low] - log_sigmas[low + 1]), 0, 1)
  return (1 - weight) * low + weight * (low + 1)


def vp_scales(sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """VE sigma -> (alpha_t, sigma_t) = (1 / sqrt(sigma² + 1), sigma * alpha_t), float32."""
  alpha = np.float32(1) / np.sqrt(sigma * sigma + np.float32(1))
  return alpha, sigma * alpha
