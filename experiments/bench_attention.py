"""XLA's attention over blocks of keys (an online softmax) and the fused CPU kernel against each
query chunk seeing every key.

  python experiments/bench_attention.py [--parts attention unet shipped_sheet] [--repeats 5] \
      [--attention_repeats 15] [--name bench_attention]

In XLA's ops (`AttentionOptions.cpu_kernel` False) `key_chunk_size` splits each query chunk's
keys into blocks; at least the key count (ALL_KEYS) gives the earlier path, every chunk against
all keys at once. The default options run the fused kernel (cpu_attention.py). Three parts; the
first two time the programs in one process, alternating call by call, each compiled with the
float32 sampler's options (`sampler.CPU_FLOAT32_COMPILER_OPTIONS`):
  attention  one SD 1.5 self-attention at the 64x64 latent's first two UNet levels (batch 2 as
             under classifier-free guidance: [2, 4096, 8, 40] and [2, 1024, 8, 80]) for query
             chunks of 512 and 1,024 against key blocks of 256 to 2,048 and ALL_KEYS, and the
             kernel;
  unet       bench_diffusion's SD 1.5 UNet forward at 32x32 and 64x64 latents: the kernel, XLA's
             default options and ALL_KEYS;
  shipped_sheet  whether the shipped model's 2 x 3 sheet sampler (bench_sampler_options.py's
             sampling, one sheet and four) lowers to the same program with XLA's default options
             and ALL_KEYS: its attention sees at most 384 keys, fewer than a block, so nothing
             changes there.
Each program's calls after a warm-up are recorded with their median, and the median of the
per-round speed-ups over the ALL_KEYS program (its seconds over the other's), with their range,
and the largest difference between the programs' outputs. Writes NAME.json with the machine and
load, and NAME.png: the speed-ups (when a part was timed), into --results DIR (default
outputs/experiments/).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import time
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

import bench_winograd_compile
import machine
import plotting
import results_dir
from bench_diffusion import SD15_UNET
from signerf_jax import files
from signerf_jax.diffusion import model_configs, pipeline, sampler, weights
from signerf_jax.diffusion.attention import AttentionOptions, dot_product_attention
from signerf_jax.diffusion.unet import UNet2DCondition
from signerf_jax.editing.config import DEFAULT_MODEL_DIR

ALL_KEYS = 2**31
KERNEL = AttentionOptions()
XLA = dataclasses.replace(KERNEL, cpu_kernel=False)
EVERY_KEY = dataclasses.replace(XLA, key_chunk_size=ALL_KEYS)
# [batch, tokens, heads, head dim] of the SD 1.5 UNet's self-attention at a 64x64 latent.
ATTENTION_SHAPES = {"sd15_64x64_level_0": (2, 4096, 8, 40), "sd15_64x64_level_1": (2, 1024, 8, 80)}
QUERY_CHUNKS = (512, 1024)
KEY_BLOCKS = (256, 512, 1024, 2048, ALL_KEYS)


def label(options: AttentionOptions) -> str:
  if options.cpu_kernel:
    return "fused CPU kernel"
  keys = "all" if options.key_chunk_size == ALL_KEYS else options.key_chunk_size
  return f"queries {options.query_chunk_size}, keys {keys}"


def alternate(calls: dict[str, Callable[[int], Any]], baseline: str,
              repeats: int) -> dict[str, Any]:
  """Times `calls` (name -> function of the round, returning what to block on) in turn, one
  warm-up round then `repeats`; each one's seconds, median and speed-up over `baseline`."""
  for call in calls.values():
    jax.block_until_ready(call(0))
  seconds = {name: [] for name in calls}
  for round_index in range(1, repeats + 1):
    for name, call in calls.items():
      start = time.perf_counter()
      jax.block_until_ready(call(round_index))
      seconds[name].append(round(time.perf_counter() - start, 4))
  summary = {}
  for name, measured in seconds.items():
    ratios = [base / own for base, own in zip(seconds[baseline], measured)]
    summary[name] = {"seconds": measured, "median_seconds": statistics.median(measured),
                     "speedup_over_baseline": round(statistics.median(ratios), 3),
                     "speedup_range": [round(min(ratios), 3), round(max(ratios), 3)]}
  return summary


def compiled(function, arguments):
  """`function` compiled for `arguments` as the float32 sampler is."""
  return jax.jit(function, compiler_options=sampler.CPU_FLOAT32_COMPILER_OPTIONS).lower(
      *arguments).compile()


def attention_part(repeats: int) -> dict[str, Any]:
  """Every query chunk x key block on each of ATTENTION_SHAPES (the module docstring)."""
  results = {}
  random = np.random.default_rng(0)
  for shape_name, shape in ATTENTION_SHAPES.items():
    query, key, value = (jnp.asarray(random.standard_normal(shape), jnp.float32)
                         for _ in range(3))
    settings = [dataclasses.replace(XLA, query_chunk_size=chunk, key_chunk_size=block)
                for chunk in QUERY_CHUNKS for block in KEY_BLOCKS] + [KERNEL]
    programs = {label(options): compiled(
        lambda q, k, v, options=options: dot_product_attention(q, k, v, options),
        (query, key, value)) for options in settings}
    expected = programs[label(EVERY_KEY)](query, key, value)
    results[shape_name] = {
        "shape": shape,
        "max_abs_difference": max(float(jnp.abs(program(query, key, value) - expected).max())
                                  for program in programs.values()),
        "programs": alternate({name: lambda _, program=program: program(query, key, value)
                               for name, program in programs.items()}, label(EVERY_KEY),
                              repeats)}
    print(shape_name, {name: measured["speedup_over_baseline"]
                       for name, measured in results[shape_name]["programs"].items()}, flush=True)
  return results


def unet_part(repeats: int) -> dict[str, Any]:
  """The SD 1.5 UNet's forward with the kernel, XLA's default options and ALL_KEYS."""
  results = {}
  random = np.random.default_rng(0)
  config = model_configs.UNetConfig.from_dict(SD15_UNET)
  params = weights.random_params(UNet2DCondition(config))
  for size in (32, 64):
    arguments = (params, jnp.asarray(random.standard_normal((2, size, size, 4)), jnp.float32),
                 jnp.full((2,), 500), jnp.asarray(random.standard_normal((2, 77, 768)),
                                                  jnp.float32))
    programs = {}
    for options in (KERNEL, XLA, EVERY_KEY):
      module = UNet2DCondition(config, attention=options)
      programs[label(options)] = compiled(
          lambda p, x, t, c, module=module: module.apply({"params": p}, x, t, c), arguments)
    outputs = [program(*arguments) for program in programs.values()]
    results[f"sd15_unet_{size}x{size}"] = {
        "max_abs_difference": max(float(jnp.abs(output - outputs[-1]).max())
                                  for output in outputs),
        "programs": alternate({name: lambda _, program=program: program(*arguments)
                               for name, program in programs.items()}, label(EVERY_KEY),
                              repeats)}
    print(size, results[f"sd15_unet_{size}x{size}"], flush=True)
  return results


def shipped_sheet_part(repeats: int) -> dict[str, Any]:
  """Whether the shipped model's sheet sampler (bench_sampler_options.py's sampling) lowers to
  the same program with XLA's default options and ALL_KEYS; `repeats` is unused (nothing is
  timed)."""
  del repeats
  results = {}
  loaded = {label(options): pipeline.load_pipeline(DEFAULT_MODEL_DIR, attention=options)
            for options in (XLA, EVERY_KEY)}
  for batch, winograd in ((1, False), (4, True)):
    programs = []
    for models in loaded.values():
      arguments, noise, setup = bench_winograd_compile.sheet_sampling(models, batch, winograd)
      programs.append(sampler.program(models.models).lower(
          *arguments, noise(0), setup.guidance, settings=setup.settings).as_text())
    results[f"batch_{batch}"] = {"winograd_convolutions": winograd,
                                 "identical_programs": programs[0] == programs[1]}
  print("shipped sheet", results, flush=True)
  return results


PARTS = {"attention": attention_part, "unet": unet_part, "shipped_sheet": shipped_sheet_part}


def write_figure(path: Path, result: dict[str, Any]) -> None:
  """One panel per timed workload: each option's median speed-up over every key at once, the
  line spanning the rounds'."""
  short = lambda name: name.replace("queries ", "q").replace(", keys ", " k")
  panels = {workload: [(short(name), measured["speedup_over_baseline"],
                        *measured["speedup_range"])
                       for name, measured in found["programs"].items()
                       if name != label(EVERY_KEY)]
            for part in result["parts"].values() for workload, found in part.items()
            if "programs" in found}
  if not panels:  # Only shipped_sheet ran: nothing was timed.
    return
  height = 90 + 18 * max(len(rows) for rows in panels.values())
  plotting.write_panels(path, [plotting.interval_chart(workload, rows,
                                                       "x every key at once", height=height)
                               for workload, rows in panels.items()])


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--parts", nargs="+", choices=list(PARTS), default=list(PARTS))
  parser.add_argument("--repeats", type=int, default=5,
                      help="timed calls of each program (the UNet's)")
  parser.add_argument("--attention_repeats", type=int, default=15,
                      help="timed calls of each single-attention program")
  parser.add_argument("--name", default="bench_attention", help="results/<name>.json")
  results_dir.add_argument(parser)
  args = parser.parse_args()
  result = {"what": __doc__.split("\n\n")[2].replace("\n", " "),
            "default": dataclasses.asdict(KERNEL), "machine": machine.record(),
            "repeats": args.repeats, "attention_repeats": args.attention_repeats, "parts": {}}
  for part in args.parts:
    result["parts"][part] = PARTS[part](
        args.attention_repeats if part == "attention" else args.repeats)
  result["machine"]["load_average_at_end"] = os.getloadavg()
  files.write_json(args.results / f"{args.name}.json", result)
  write_figure(args.results / f"{args.name}.png", result)
  print(f"bench_attention: results in {args.results / args.name}.{{json,png}}")


if __name__ == "__main__":
  main()
