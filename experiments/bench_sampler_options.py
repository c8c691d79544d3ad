"""The sampler compiled with its own XLA options against XLA's defaults, on the shipped model.

  python experiments/bench_sampler_options.py [--repeats 5] [--precisions float32 bfloat16] \
      [--name bench_sampler_options]

The sampler of float32 models is compiled with `sampler.CPU_FLOAT32_COMPILER_OPTIONS` (XLA:CPU's
matmuls kept out of YNNPACK), that of bfloat16 models with XLA's defaults. This samples the
shipped model's 2 x 3 sheet of 64-px tiles (128 x 192 pixels, 20 DPM-Solver steps, guidance 7.5,
ControlNet) with `sampler.sample` compiled both ways, in one process, the two alternating call by
call (new noise each call), at the preview's batch of one sheet (compiled without Winograd
convolutions, as the preview compiles it) and the image set update's batch of four (with them),
for each compute precision asked for (bfloat16: the weights stored in bfloat16, as
`EditConfig.diffusion_precision` loads them). It records the seconds of every call after the
first and their median, the median ratio, and the largest difference between the two programs'
images; not compilation seconds, which in one process depend on the order (the first program
compiled pays the process's one-off costs; bench_winograd_compile.py measures them in fresh
processes). Writes NAME.json with the machine and load into --results DIR (default
outputs/experiments/).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

import bench_winograd_compile
import machine
import results_dir
from signerf_jax import files
from signerf_jax.diffusion import pipeline, sampler
from signerf_jax.editing.config import DEFAULT_MODEL_DIR

PRECISIONS = {"float32": (np.float32, jnp.float32), "bfloat16": (jnp.bfloat16, jnp.bfloat16)}
# Batch -> whether its program uses Winograd convolutions, as the preview and the update do.
BATCHES = {1: False, 4: True}


# The two ways of compiling `sampler.sample` (its own jit is inlined into these).
OPTIONS = {"without_ynnpack": sampler.CPU_FLOAT32_COMPILER_OPTIONS, "xla_default": None}


def measure(loaded: pipeline.Pipeline, batch: int, winograd: bool, repeats: int) -> dict:
  """Both programs' sampling seconds for `batch` sheets (see the docstring)."""
  arguments, noise, setup = bench_winograd_compile.sheet_sampling(loaded, batch, winograd)
  programs = {name: jax.jit(sampler.sample, static_argnames=("settings",),
                            compiler_options=options).lower(
                                *arguments, noise(0), setup.guidance,
                                settings=setup.settings).compile()
              for name, options in OPTIONS.items()}
  images = {name: np.asarray(program(*arguments, noise(0), setup.guidance))
            for name, program in programs.items()}
  call_seconds = {name: [] for name in programs}
  for seed in range(1, repeats + 1):
    for name, program in programs.items():
      start = time.perf_counter()
      program(*arguments, noise(seed), setup.guidance).block_until_ready()
      call_seconds[name].append(round(time.perf_counter() - start, 3))
  median = {name: statistics.median(seconds) for name, seconds in call_seconds.items()}
  return {"batch": batch, "winograd_convolutions": winograd, "call_seconds": call_seconds,
          "median_call_seconds": median,
          "xla_default_over_without_ynnpack": round(median["xla_default"]
                                                    / median["without_ynnpack"], 3),
          "max_abs_image_difference": float(np.abs(images["without_ynnpack"]
                                                   - images["xla_default"]).max())}


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--repeats", type=int, default=5, help="timed calls of each program")
  parser.add_argument("--precisions", nargs="+", choices=list(PRECISIONS),
                      default=list(PRECISIONS))
  parser.add_argument("--name", default="bench_sampler_options")
  results_dir.add_argument(parser)
  args = parser.parse_args()
  record = {"what": __doc__.split("\n\n")[2].replace("\n", " "),
            "compiler_options": sampler.CPU_FLOAT32_COMPILER_OPTIONS, "machine": machine.record(),
            "runs": []}
  for precision in args.precisions:
    dtype, compute_dtype = PRECISIONS[precision]
    loaded = pipeline.load_pipeline(DEFAULT_MODEL_DIR, dtype=dtype, compute_dtype=compute_dtype)
    for batch, winograd in BATCHES.items():
      record["runs"].append({"precision": precision,
                             **measure(loaded, batch, winograd, args.repeats)})
      print(record["runs"][-1], flush=True)
  record["machine"]["load_average_at_end"] = os.getloadavg()
  files.write_json(args.results / f"{args.name}.json", record)


if __name__ == "__main__":
  main()
