"""Speed of the Flax UNet (and UNet + ControlNet) against diffusers/torch on this CPU.

For an SD1.5-shaped UNet (block_out_channels 320/640/1280/1280, cross_attention_dim 768, batch 2
as under classifier-free guidance, text states (2, 77, 768)) at each latent size: seconds per
forward of our jitted model and of diffusers (torch, `threads` threads), their ratio
`jax_over_torch`, compile time, FLOPs (counted by torch's FlopCounterMode on the reference
forward) and achieved GFLOP/s against the CPU's fp32 peak as this run measures it (the best
GFLOP/s of large jitted fp32 matmuls, same threads: before and after the models, and at the start
of each timing round, which follows the machine's drift within the run), XLA's memory
plan, the largest output difference from torch (both run the same random weights, converted
through our loader's name and layout mapping), and the bf16-compute option's speed and error
(with the weights stored in bf16). Our forwards are compiled as the sampler compiles them
(`sampler.program`: fp32 with `sampler.CPU_FLOAT32_COMPILER_OPTIONS`, XLA:CPU's matmuls kept out of
YNNPACK; bf16 with XLA's defaults); the fp32 one is also timed compiled with XLA's defaults
(`xla_default_options`), side by side.
JAX and torch runs alternate and medians are reported, so a busy machine slows both alike;
process CPU seconds per forward are recorded too. With `benchmark.threads = 1` both run
single-threaded, whose CPU time is the measure least disturbed by other jobs on a shared
machine.

    python experiments/bench_diffusion.py [--gin_file bench_diffusion] [--gin_param ...]

Writes bench_diffusion.json and bench_diffusion.gin (atomically) into --results DIR (default
outputs/experiments/), or --output JSON and the .gin beside it.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import resource
import statistics
import sys
import time
from pathlib import Path
from typing import Callable

import gin
import jax
import jax.numpy as jnp
import numpy as np

import machine
import results_dir
from signerf_jax import configs, files
from signerf_jax.diffusion import model_configs, sampler, weights
from signerf_jax.diffusion.attention import AttentionOptions
from signerf_jax.diffusion.controlnet import ControlNet
from signerf_jax.diffusion.unet import UNet2DCondition

# The square fp32 matmul that measures the peak (2 n^3 FLOPs; ~0.1 s here), and how often.
PEAK_MATMUL_SIZE = 2048
PEAK_REPEATS = 10
SD15_UNET = dict(block_out_channels=(320, 640, 1280, 1280), cross_attention_dim=768,
                 attention_head_dim=8, layers_per_block=2, sample_size=64)


def hide_unloadable_torchvision() -> None:
  """diffusers imports transformers, which imports torchvision when installed; a torchvision
  built for another torch (PyPI's CUDA wheel next to the CPU torch) fails to load. The benchmark
  does not need it, so a broken one is made to look absent."""
  try:
    import torchvision  # pylint: disable=g-import-not-at-top,unused-import
  except (ImportError, RuntimeError, OSError):
    for name in [name for name in sys.modules if name.split(".")[0] == "torchvision"]:
      del sys.modules[name]
    sys.modules["torchvision"] = None


def seconds(function) -> float:
  start = time.perf_counter()
  function()
  return time.perf_counter() - start


def wall_and_cpu_seconds(function) -> tuple[float, float]:
  wall, cpu = time.perf_counter(), time.process_time()
  function()
  return time.perf_counter() - wall, time.process_time() - cpu


def perturb_zero_parameters(model, seed: int = 0):
  """Random noise on parameters diffusers initialises to zero (ControlNet zero-convs), so the
  residuals -- and a wrong mapping -- are visible in the output."""
  import torch  # pylint: disable=g-import-not-at-top
  generator = torch.Generator().manual_seed(seed)
  with torch.no_grad():
    for parameter in model.parameters():
      if not parameter.any():
        parameter.add_(0.02 * torch.randn(parameter.shape, generator=generator))
  return model.eval()


def flax_params(module, torch_model):
  """Our params from a torch model's state dict, through the loader's name/layout mapping."""
  tensors = {name: tensor.detach().numpy() for name, tensor in torch_model.state_dict().items()}
  return weights.params_from_tensors(module, tensors, type(torch_model).__name__)


def peak_meter(size: int = PEAK_MATMUL_SIZE, repeats: int = PEAK_REPEATS
               ) -> Callable[[], float]:
  """A function returning the best GFLOP/s of `repeats` jitted [size, size] fp32 matmuls (compiled
  once): the peak a dense kernel reaches on this machine with the threads XLA uses, now (a
  2048^3 matmul reached 81% of an AVX-512 FMA loop's 233 GFLOP/s here:
  ../shared/notes/cpu-performance.md)."""
  keys = jax.random.split(jax.random.PRNGKey(0))
  left, right = (jax.random.normal(key, (size, size), jnp.float32) for key in keys)
  multiply = jax.jit(jnp.matmul).lower(left, right).compile()
  jax.block_until_ready(multiply(left, right))

  def measure() -> float:
    best = min(seconds(lambda: jax.block_until_ready(multiply(left, right)))
               for _ in range(repeats))
    return 2 * size**3 / 1e9 / best
  return measure


def reference_flops(forward) -> float:
  from torch.utils.flop_counter import FlopCounterMode  # pylint: disable=g-import-not-at-top
  counter = FlopCounterMode(display=False)
  with counter:
    forward()
  return float(counter.get_total_flops())


def memory_plan(compiled) -> dict[str, int]:
  analysis = compiled.memory_analysis()
  return {"temporaries_bytes": int(analysis.temp_size_in_bytes),
          "arguments_bytes": int(analysis.argument_size_in_bytes),
          "outputs_bytes": int(analysis.output_size_in_bytes)}


def time_side_by_side(forwards: dict, repeats: int,
                      measure_peak: Callable[[], float]) -> dict[str, list[float]]:
  """Wall and process-CPU seconds of each named forward, the forwards alternating, and the peak
  GFLOP/s measured at the start of each round (`peak_gflops_per_second_all`)."""
  times = {"peak_gflops_per_second_all": []}
  for _ in range(repeats):
    times["peak_gflops_per_second_all"].append(measure_peak())
    for name, forward in forwards.items():
      wall, cpu = wall_and_cpu_seconds(forward)
      times.setdefault(f"{name}_seconds_all", []).append(wall)
      times.setdefault(f"{name}_cpu_seconds_all", []).append(cpu)
  return times


def compare(name, jax_function, jax_args, torch_forward, torch_output, flops, repeats,
            peak_gflops: float, measure_peak: Callable[[], float], bf16_function=None) -> dict:
  """Compiles as the sampler compiles (`sampler.program`), checks agreement, times JAX against
  torch, interleaved with the fp32 program under XLA's default options, the bf16 variant and a
  peak reading per round."""
  start = time.perf_counter()
  compiled = jax_function.lower(*jax_args).compile(
      compiler_options=sampler.CPU_FLOAT32_COMPILER_OPTIONS)
  compile_seconds = time.perf_counter() - start
  jax_output = np.asarray(compiled(*jax_args))
  difference = float(np.abs(jax_output - torch_output).max())
  start = time.perf_counter()
  xla_default = jax_function.lower(*jax_args).compile()
  xla_default_compile_seconds = time.perf_counter() - start
  xla_default_difference = float(np.abs(np.asarray(xla_default(*jax_args)) - jax_output).max())
  forwards = {"jax": lambda: jax.block_until_ready(compiled(*jax_args)), "torch": torch_forward,
              "xla_default": lambda: jax.block_until_ready(xla_default(*jax_args))}
  if bf16_function is not None:
    # Weights stored in bf16, as `load_pipeline(dtype=bfloat16)` stores them: cast once, not in
    # every forward (which costs 22-52% of a bf16 forward: profile_diffusion.json).
    bf16_args = (jax.tree.map(lambda leaf: leaf.astype(jnp.bfloat16), jax_args[0]),
                 *jax_args[1:])
    bf16 = bf16_function.lower(*bf16_args).compile()
    bf16_output = np.asarray(bf16(*bf16_args))
    forwards["bf16"] = lambda: jax.block_until_ready(bf16(*bf16_args))
  times = time_side_by_side(forwards, repeats, measure_peak)
  median = {key: statistics.median(times[f"{key}_seconds_all"]) for key in forwards}
  round_peaks = times.pop("peak_gflops_per_second_all")
  result = {
      "jax_seconds": median["jax"], "torch_seconds": median["torch"],
      "jax_over_torch": median["jax"] / median["torch"],
      "jax_cpu_seconds": statistics.median(times["jax_cpu_seconds_all"]),
      "torch_cpu_seconds": statistics.median(times["torch_cpu_seconds_all"]),
      "compile_seconds": compile_seconds, "gflop": flops / 1e9,
      "jax_gflops_per_second": flops / 1e9 / median["jax"],
      "torch_gflops_per_second": flops / 1e9 / median["torch"],
      "jax_fraction_of_measured_peak": flops / 1e9 / median["jax"] / peak_gflops,
      # The same against the peak read just before each JAX forward, which follows the
      # machine's speed through the run (a shared host's 2,048^2 matmul read 93-155 GFLOP/s
      # from one round to the next).
      "jax_fraction_of_round_peak": statistics.median(
          flops / 1e9 / wall / peak for wall, peak in zip(times["jax_seconds_all"], round_peaks)),
      "round_peaks_gflops_per_second": round_peaks,
      "jax_memory_plan": memory_plan(compiled),
      "max_abs_difference_from_torch": difference,
      "output_abs_max": float(np.abs(torch_output).max()),
      **{key: value for key, value in times.items() if key.split("_")[0] in ("jax", "torch")},
      "xla_default_options": {
          "seconds": median["xla_default"], "seconds_all": times["xla_default_seconds_all"],
          "compile_seconds": xla_default_compile_seconds,
          "max_abs_difference": xla_default_difference,
          "over_sampler_options": median["xla_default"] / median["jax"]},
  }
  if bf16_function is not None:
    error = np.abs(bf16_output - jax_output)
    result["bf16"] = {
        "seconds": median["bf16"], "seconds_all": times["bf16_seconds_all"],
        "cpu_seconds": statistics.median(times["bf16_cpu_seconds_all"]),
        "speedup_over_fp32": median["jax"] / median["bf16"],
        "max_abs_error_vs_fp32": float(error.max()),
        "relative_rms_error_vs_fp32": float(np.sqrt(np.mean(error**2) / np.mean(jax_output**2))),
    }
  print(f"{name}: jax {median['jax']:.3f} s, torch {median['torch']:.3f} s, "
        f"ratio {result['jax_over_torch']:.3f}, compile {compile_seconds:.1f} s, "
        f"{result['jax_gflops_per_second']:.0f} GFLOP/s, diff {difference:.2e}, "
        f"XLA's defaults {median['xla_default']:.3f} s"
        + (f", bf16 {median['bf16']:.3f} s" if "bf16" in result else ""), flush=True)
  return result


@gin.configurable
def benchmark(latent_sizes=(32, 64), batch: int = 2, repeats: int = 5, threads: int = 2,
              models=("unet", "unet_controlnet"), bf16: bool = True, seed: int = 0) -> dict:
  """Runs the comparisons; returns the JSON-ready results.

  Args:
    threads: torch's thread count; 1 also makes XLA single-threaded (it must then run before
      anything initialises JAX's CPU backend, as `main` ensures).
  """
  if threads == 1:
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") +
                               " --xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")
  hide_unloadable_torchvision()
  import diffusers  # pylint: disable=g-import-not-at-top
  import torch  # pylint: disable=g-import-not-at-top

  torch.set_num_threads(threads)
  torch.manual_seed(seed)
  torch_unet = diffusers.UNet2DConditionModel(**SD15_UNET).eval()
  attention = configs.build(AttentionOptions)
  unet_config = model_configs.UNetConfig.from_dict(dict(torch_unet.config))
  unet = UNet2DCondition(unet_config, attention)
  unet_bf16 = dataclasses.replace(unet, compute_dtype=jnp.bfloat16)
  unet_params = flax_params(unet, torch_unet)
  if "unet_controlnet" in models:
    torch_controlnet = perturb_zero_parameters(
        diffusers.ControlNetModel.from_unet(torch_unet, conditioning_channels=3), seed)
    controlnet = ControlNet(model_configs.ControlNetConfig.from_dict(
        dict(torch_controlnet.config)), attention)
    controlnet_bf16 = dataclasses.replace(controlnet, compute_dtype=jnp.bfloat16)
    controlnet_params = flax_params(controlnet, torch_controlnet)

  def unet_function(module):
    return jax.jit(lambda params, sample, timesteps, context: module.apply(
        {"params": params}, sample, timesteps, context))

  def controlled_function(unet_module, controlnet_module):
    def forward(params, sample, timesteps, context, image):
      residuals = controlnet_module.apply({"params": params[1]}, sample, timesteps, context, image)
      return unet_module.apply({"params": params[0]}, sample, timesteps, context,
                               control=residuals)
    return jax.jit(forward)

  results = {}
  measure_peak = peak_meter()
  peaks = [measure_peak()]
  generator = torch.Generator().manual_seed(seed)
  for size in latent_sizes:
    sample = torch.randn(batch, 4, size, size, generator=generator)
    timesteps = torch.full((batch,), 500)
    context = torch.randn(batch, 77, 768, generator=generator)
    image = torch.rand(batch, 3, 8 * size, 8 * size, generator=generator)
    nhwc = lambda tensor: jnp.asarray(tensor.numpy().transpose(0, 2, 3, 1))
    jax_inputs = (nhwc(sample), jnp.asarray(timesteps.numpy()), jnp.asarray(context.numpy()))

    if "unet" in models:
      torch_forward = lambda: torch_unet(sample, timesteps, context).sample
      with torch.no_grad():
        torch_output = torch_forward().numpy().transpose(0, 2, 3, 1)
        flops = reference_flops(torch_forward)
        results[f"unet_{size}x{size}"] = compare(
            f"unet {size}x{size}", unet_function(unet), (unet_params,) + jax_inputs,
            torch.no_grad()(torch_forward), torch_output, flops, repeats, peaks[0],
            measure_peak, unet_function(unet_bf16) if bf16 else None)

    if "unet_controlnet" in models:
      def torch_controlled():
        down, mid = torch_controlnet(sample, timesteps, context, image, return_dict=False)
        return torch_unet(sample, timesteps, context, down_block_additional_residuals=down,
                          mid_block_additional_residual=mid).sample
      with torch.no_grad():
        torch_output = torch_controlled().numpy().transpose(0, 2, 3, 1)
        flops = reference_flops(torch_controlled)
        results[f"unet_controlnet_{size}x{size}"] = compare(
            f"unet+controlnet {size}x{size}", controlled_function(unet, controlnet),
            ((unet_params, controlnet_params),) + jax_inputs + (nhwc(image),),
            torch.no_grad()(torch_controlled), torch_output, flops, repeats, peaks[0],
            measure_peak, controlled_function(unet_bf16, controlnet_bf16) if bf16 else None)
  peaks.append(measure_peak())
  results["measured_peak"] = {
      "matmul_size": PEAK_MATMUL_SIZE, "gflops_per_second_before_after": peaks,
      "note": "jax_fraction_of_measured_peak uses the 'before' figure, "
              "jax_fraction_of_round_peak the reading at the start of each round"}
  results["attention_options"] = dataclasses.asdict(attention)
  results["threads"] = threads
  return results


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  configs.add_gin_arguments(parser)
  results_dir.add_argument(parser)
  parser.add_argument("--output", metavar="JSON",
                      help="the json to write (default: DIR/bench_diffusion.json)")
  args = parser.parse_args(argv)
  configs.parse_gin(args.gin_file or ["bench_diffusion"], args.gin_param)
  load_before = os.getloadavg()
  results = benchmark()
  results["machine"] = {
      "processor": platform.processor() or platform.machine(), "cpu": machine.cpu_model(),
      "cpu_count": os.cpu_count(),
      "jax": jax.__version__, **machine.code_version(),
      "load_average_before_after": [load_before[0], os.getloadavg()[0]],
      "process_peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
      "note": "JAX and torch runs interleave, so other jobs (see the load averages) slow both",
  }
  results["gin_config"] = gin.config_str()
  output = Path(args.output or args.results / "bench_diffusion.json")
  files.write_json(output, results)
  files.write_text(output.with_suffix(".gin"), gin.config_str())
  print(f"wrote {output}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
