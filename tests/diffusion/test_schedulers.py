"""Schedulers and solvers: parity with diffusers' DDIM, DPM-Solver++ 2M and Euler ancestral."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from signerf_jax.diffusion import schedulers, solvers
from signerf_jax.errors import InputError

# Stable Diffusion 1.x's scheduler_config.json (a PNDM config, reused by every kind).
SD_CONFIG = {"_class_name": "PNDMScheduler", "beta_start": 0.00085, "beta_end": 0.012,
             "beta_schedule": "scaled_linear", "clip_sample": False, "set_alpha_to_one": False,
             "skip_prk_steps": True, "steps_offset": 1, "num_train_timesteps": 1000,
             "trained_betas": None}
REFERENCE_CLASSES = {"ddim": "DDIMScheduler",
                     "dpm_solver_multistep": "DPMSolverMultistepScheduler",
                     "euler_ancestral": "EulerAncestralDiscreteScheduler"}
LATENT_SHAPE = (1, 4, 6, 6)


def reference_scheduler(kind, options):
  diffusers = pytest.importorskip("diffusers")
  return getattr(diffusers, REFERENCE_CLASSES[kind]).from_config({**SD_CONFIG, **options})


def pipeline_first_step(num_steps, strength):
  """diffusers' StableDiffusion*Pipeline.get_timesteps, written out independently."""
  return max(num_steps - min(int(num_steps * strength), num_steps), 0)


def dummy_model(model_input, timestep, cos):
  return 0.1 * model_input * cos(timestep)


@jax.jit
def sampling_loop(schedule, latents, step_noise):
  """The whole denoising loop under lax.scan; returns the sample after every step."""
  def body(carry, inputs):
    sample, solver_state = carry
    step_index, noise = inputs
    model_output = dummy_model(schedule.scale_model_input(sample, step_index),
                               schedule.timesteps[step_index], jnp.cos)
    sample, solver_state = schedule.step(solver_state, step_index, model_output, sample,
                                         noise=noise)
    return (sample, solver_state), sample

  carry = (latents, schedule.init_solver_state(latents))
  _, samples = jax.lax.scan(body, carry, (jnp.arange(schedule.num_steps), step_noise))
  return samples


def run_reference(kind, options, num_steps, strength, clean, noise):
  """diffusers' scheduler driven the way its inpainting pipelines drive it."""
  import torch  # pylint: disable=g-import-not-at-top
  scheduler = reference_scheduler(kind, options)
  scheduler.set_timesteps(num_steps)
  first_step = pipeline_first_step(num_steps, strength)
  timesteps = scheduler.timesteps[first_step:]
  if hasattr(scheduler, "set_begin_index"):
    scheduler.set_begin_index(first_step)
  clean, noise = torch.from_numpy(clean), torch.from_numpy(noise)
  if strength == 1.0:
    sample = noise * scheduler.init_noise_sigma
  else:
    sample = scheduler.add_noise(clean, noise, timesteps[:1])
  generator = torch.Generator().manual_seed(0)
  record = {"initial": sample.numpy(), "inputs": [], "outputs": [], "samples": [],
            "blended": []}
  for index, timestep in enumerate(timesteps):
    model_output = dummy_model(scheduler.scale_model_input(sample, timestep),
                               timestep.to(torch.float32), torch.cos)
    record["inputs"].append(sample.numpy())
    record["outputs"].append(model_output.numpy())
    sample = scheduler.step(model_output, timestep, sample, generator=generator).prev_sample
    record["samples"].append(sample.numpy())
    if index + 1 < len(timesteps):  # The 4-channel inpainting blend re-noises the original.
      record["blended"].append(
          scheduler.add_noise(clean, noise, timesteps[index + 1:index + 2]).numpy())
  # The ancestral sampler drew its noise from this generator: replay the same draws.
  generator = torch.Generator().manual_seed(0)
  record["step_noise"] = np.stack([
      torch.randn(LATENT_SHAPE, generator=generator).numpy() if kind == "euler_ancestral"
      else np.zeros(LATENT_SHAPE, np.float32) for _ in timesteps])
  return timesteps.numpy(), record


@pytest.mark.parity
@pytest.mark.parametrize("beta_schedule", ["scaled_linear", "linear"])
def test_alphas_cumprod_are_bitwise_equal(beta_schedule):
  reference = reference_scheduler("ddim", {"beta_schedule": beta_schedule})
  config = schedulers.scheduler_config({**SD_CONFIG, "beta_schedule": beta_schedule}, "ddim")
  np.testing.assert_array_equal(schedulers.alphas_cumprod(config),
                                reference.alphas_cumprod.numpy())


@pytest.mark.parity
@pytest.mark.parametrize("kind, options", [
    ("ddim", {}), ("dpm_solver_multistep", {}),
    ("dpm_solver_multistep", {"use_karras_sigmas": True}),
    ("dpm_solver_multistep", {"final_sigmas_type": "sigma_min", "euler_at_final": True}),
    ("euler_ancestral", {}),
])
@pytest.mark.parametrize("spacing", ["leading", "trailing", "linspace"])
def test_timesteps_and_noise_levels(kind, options, spacing):
  for beta_schedule in ("scaled_linear", "linear"):
    for num_steps in (1, 2, 3, 10, 50):
      for strength in (1.0, 0.5):
        if pipeline_first_step(num_steps, strength) == num_steps:
          continue
        full = {**options, "timestep_spacing": spacing, "beta_schedule": beta_schedule}
        reference = reference_scheduler(kind, full)
        reference.set_timesteps(num_steps)
        first_step = pipeline_first_step(num_steps, strength)
        schedule = solvers.make_schedule(schedulers.scheduler_config(SD_CONFIG, kind, **full),
                                         num_steps, strength)
        case = f"{beta_schedule} {num_steps} steps strength {strength}"
        timesteps = reference.timesteps[first_step:].numpy()
        np.testing.assert_array_equal(schedule.timesteps, timesteps, err_msg=case)
        if kind == "ddim":
          np.testing.assert_allclose(schedule.alpha_cumprod,
                                     reference.alphas_cumprod[timesteps].numpy(), rtol=1e-6)
        else:
          np.testing.assert_allclose(schedule.sigmas, reference.sigmas[first_step:].numpy(),
                                     rtol=1e-6, err_msg=case)
        np.testing.assert_allclose(schedule.init_noise_sigma, float(reference.init_noise_sigma),
                                   rtol=1e-6, err_msg=case)


LOOP_CASES = [
    # kind, options, num_steps, strength
    ("ddim", {}, 1, 1.0),
    ("ddim", {"prediction_type": "v_prediction", "timestep_spacing": "trailing"}, 3, 1.0),
    ("ddim", {"timestep_spacing": "linspace"}, 4, 0.6),
    ("ddim", {"clip_sample": True, "clip_sample_range": 0.5}, 2, 1.0),
    ("ddim", {"beta_schedule": "linear", "set_alpha_to_one": True}, 8, 0.75),
    ("ddim", {"set_alpha_to_one": True}, 20, 0.75),
    ("dpm_solver_multistep", {}, 1, 1.0),
    ("dpm_solver_multistep", {"timestep_spacing": "leading"}, 2, 1.0),
    ("dpm_solver_multistep", {"prediction_type": "v_prediction",
                              "timestep_spacing": "trailing"}, 3, 1.0),
    ("dpm_solver_multistep", {"use_karras_sigmas": True}, 4, 0.6),
    ("dpm_solver_multistep", {"use_karras_sigmas": True, "prediction_type": "v_prediction",
                              "timestep_spacing": "trailing"}, 20, 1.0),
    ("dpm_solver_multistep", {"final_sigmas_type": "sigma_min", "lower_order_final": False},
     16, 0.75),
    ("dpm_solver_multistep", {"solver_order": 1, "timestep_spacing": "leading"}, 5, 1.0),
    ("euler_ancestral", {}, 1, 1.0),
    ("euler_ancestral", {"timestep_spacing": "leading"}, 3, 1.0),
    ("euler_ancestral", {"prediction_type": "v_prediction", "timestep_spacing": "trailing"}, 2,
     1.0),
    ("euler_ancestral", {"beta_schedule": "linear"}, 20, 0.6),
]


@pytest.mark.parity
@pytest.mark.parametrize("kind, options, num_steps, strength", LOOP_CASES)
def test_steps_and_loop_match_reference(kind, options, num_steps, strength):
  rng = np.random.default_rng(num_steps)
  clean = rng.standard_normal(LATENT_SHAPE).astype(np.float32)
  noise = rng.standard_normal(LATENT_SHAPE).astype(np.float32)
  timesteps, record = run_reference(kind, options, num_steps, strength, clean, noise)
  schedule = solvers.make_schedule(schedulers.scheduler_config(SD_CONFIG, kind, **options),
                                   num_steps, strength)
  np.testing.assert_array_equal(schedule.timesteps, timesteps)

  if strength == 1.0:
    initial = noise * schedule.init_noise_sigma
  else:
    initial = schedule.add_noise(clean, noise, 0)
  np.testing.assert_allclose(initial, record["initial"], atol=1e-5, rtol=0)

  # Each step on the reference's inputs (eager, with our solver memory).
  solver_state = schedule.init_solver_state(jnp.asarray(initial))
  for index in range(schedule.num_steps):
    sample, solver_state = schedule.step(solver_state, index, record["outputs"][index],
                                         record["inputs"][index],
                                         noise=record["step_noise"][index])
    np.testing.assert_allclose(sample, record["samples"][index], atol=1e-5, rtol=0,
                               err_msg=f"step {index}")
    if index + 1 < schedule.num_steps:
      np.testing.assert_allclose(schedule.add_noise(clean, noise, index + 1),
                                 record["blended"][index], atol=1e-5, rtol=0)

  # The compiled loop on its own.
  samples = sampling_loop(schedule, jnp.asarray(record["initial"]), record["step_noise"])
  np.testing.assert_allclose(samples, np.stack(record["samples"]), atol=1e-5, rtol=0)


def test_loop_does_not_recompile_for_another_schedule_of_the_same_shape():
  config = schedulers.scheduler_config(SD_CONFIG, "dpm_solver_multistep")
  latents = jnp.ones(LATENT_SHAPE)
  step_noise = jnp.zeros((4, *LATENT_SHAPE))
  sampling_loop(solvers.make_schedule(config, 4), latents, step_noise)
  cache_size = sampling_loop._cache_size()  # pylint: disable=protected-access
  karras = schedulers.scheduler_config(SD_CONFIG, "dpm_solver_multistep", use_karras_sigmas=True)
  samples = sampling_loop(solvers.make_schedule(karras, 8, strength=0.5), latents, step_noise)
  assert sampling_loop._cache_size() == cache_size  # pylint: disable=protected-access
  assert np.isfinite(samples).all()


def test_euler_ancestral_noise_from_key():
  schedule = solvers.make_schedule(schedulers.scheduler_config(SD_CONFIG, "euler_ancestral"), 5)
  sample = jnp.ones(LATENT_SHAPE)
  output = 0.5 * sample
  key = jax.random.key(3)
  drawn, _ = schedule.step((), 1, output, sample, key=key)
  given, _ = schedule.step((), 1, output, sample, noise=jax.random.normal(key, LATENT_SHAPE))
  other, _ = schedule.step((), 1, output, sample, key=jax.random.key(4))
  np.testing.assert_array_equal(drawn, given)
  assert not np.allclose(drawn, other)
  with pytest.raises(ValueError, match="needs `noise` or a PRNG `key`"):
    schedule.step((), 1, output, sample)


def test_config_file_and_overrides(tmp_path):
  directory = tmp_path / "scheduler"
  directory.mkdir()
  (directory / "scheduler_config.json").write_text(json.dumps(
      {**SD_CONFIG, "_class_name": "DPMSolverMultistepScheduler", "algorithm_type": "deis"}))
  config = schedulers.load_scheduler_config(directory, use_karras_sigmas=True)
  assert config.kind == "dpm_solver_multistep" and config.use_karras_sigmas
  assert config.timestep_spacing == "linspace" and config.beta_schedule == "scaled_linear"
  ddim = schedulers.load_scheduler_config(directory / "scheduler_config.json", kind="ddim")
  assert ddim.timestep_spacing == "leading" and ddim.steps_offset == 1 and not ddim.clip_sample


@pytest.mark.parametrize("config, kind, overrides, field", [
    (SD_CONFIG, None, {}, "_class_name"),  # PNDM itself is not implemented.
    (SD_CONFIG, "heun", {}, "kind"),
    (SD_CONFIG, "ddim", {"thresholding": True}, "thresholding"),
    (SD_CONFIG, "dpm_solver_multistep", {"algorithm_type": "sde-dpmsolver++"}, "algorithm_type"),
    (SD_CONFIG, "dpm_solver_multistep", {"solver_order": 3}, "solver_order"),
    ({**SD_CONFIG, "beta_schedule": "squaredcos_cap_v2"}, "ddim", {}, "beta_schedule"),
    ({**SD_CONFIG, "prediction_type": "sample"}, "euler_ancestral", {}, "prediction_type"),
    (SD_CONFIG, "euler_ancestral", {"use_karras_sigmas": True}, "use_karras_sigmas"),
])
def test_unsupported_configurations_name_the_field(config, kind, overrides, field):
  with pytest.raises(InputError) as error:
    schedulers.scheduler_config(config, kind, source="scheduler_config.json", **overrides)
  assert error.value.field == field and error.value.path == "scheduler_config.json"


@pytest.mark.parametrize("num_steps, strength", [(0, 1.0), (1001, 1.0), (4, 0.2), (4, 1.5)])
def test_bad_step_counts_and_strengths(num_steps, strength):
  config = schedulers.scheduler_config(SD_CONFIG, "ddim")
  with pytest.raises(InputError):
    solvers.make_schedule(config, num_steps, strength)
