"""What Winograd convolutions cost in compilation and save in sampling, for the shipped model's sheet.

  python experiments/bench_winograd_compile.py [--repeats 2] [--name bench_winograd_compile]

`signerf preview` compiles its sampler without Winograd convolutions (editing/stages/sheets.py):
a user waits for the compilation and the first sheet, and the rest of the preview is a few more
sheets. This measures that choice: the shipped model's 2 x 3 sheet of 64-px tiles (128 x 192
pixels, 20 DPM-Solver steps, guidance 7.5, ControlNet), at the preview's batch of one sheet and
the image set update's batch of four, each setting in a new process (nothing compiled before; no
compilation cache), the processes of the settings alternating. It records the compilation
seconds, the first call's and the median of three later calls' seconds, which algorithm
`layers.conv2d` chose how often, and where the compiled program computes the Winograd kernel
transforms (G g G^T of every Winograd layer's weights): in the loop body they would be redone at
every denoising step for weights that do not change; XLA's loop-invariant code motion hoists them
to the program's entry. Writes NAME.json with the machine and load into --results DIR (default
outputs/experiments/).
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import re
import statistics
import subprocess
import sys
import time

import jax
import numpy as np

import machine
import results_dir
from signerf_jax import files
from signerf_jax.diffusion import layers, pipeline, sampler
from signerf_jax.editing.config import DEFAULT_MODEL_DIR

HEIGHT, WIDTH = 128, 192  # The shipped model's 2 x 3 sheet of 64-px tiles.
PROMPT = "a teddy bear"


def kernel_transforms_by_place(hlo_text: str) -> dict[str, int]:
  """How many fusions turning a [3, 3, C, O] kernel into a Winograd domain [m + 2, ...] array the
  optimised HLO `hlo_text` calls from its entry computation and from any other (loop bodies)."""
  computations = re.split(r"\n(?=(?:ENTRY )?%[\w.\-]+ [({])", hlo_text)
  transforms = set()
  for computation in computations:
    header = computation.split("\n", 1)[0]
    if (re.search(r"\([^)]*f32\[3,3,\d+,\d+\]", header)
        and re.search(r"-> f32\[(4|6),(3|4|6),\d+,\d+\]", header)):
      transforms.add(header.split(" ", 1)[0])
  places = collections.Counter()
  for computation in computations:
    calls = sum(len(re.findall(rf"calls={re.escape(name)}\b", computation))
                for name in transforms)
    places["entry" if computation.startswith("ENTRY") else "elsewhere"] += calls
  return dict(places)


def sheet_sampling(loaded: pipeline.Pipeline, batch: int, winograd: bool):
  """What sampling `batch` random sheets of HEIGHT x WIDTH with `loaded` takes: `sampler.sample`'s
  arguments before the noise, a function from a seed to the noise, and `pipeline.sampler_setup`'s
  result (its guidance and settings complete the arguments)."""
  prompt = pipeline.encode_prompts(loaded, PROMPT)
  setup = pipeline.sampler_setup(loaded, HEIGHT, WIDTH, pipeline.GenerationOptions(), winograd)
  random = np.random.default_rng(0)
  inputs = sampler.InpaintingInputs(random.random((batch, HEIGHT, WIDTH, 3), np.float32),
                                    np.ones((batch, HEIGHT, WIDTH, 1), np.float32),
                                    random.random((batch, HEIGHT, WIDTH, 1), np.float32))
  factor = loaded.models.latent_factor

  def noise(seed: int) -> sampler.SamplerNoise:
    return sampler.draw_noise(jax.random.split(jax.random.key(seed), batch),
                              (HEIGHT // factor, WIDTH // factor, loaded.models.latent_channels),
                              setup.schedule.num_steps)

  return (loaded.models, setup.schedule, prompt, setup.time_ids, inputs), noise, setup


def measure(batch: int, winograd: bool) -> dict:
  """Compiles and runs the sheet sampler once per process (see the module docstring)."""
  algorithms = collections.Counter()
  choose = layers.convolution_algorithm

  def counting_choice(*args, **kwargs):
    algorithm = choose(*args, **kwargs)
    algorithms[algorithm] += 1
    return algorithm

  layers.convolution_algorithm = counting_choice
  loaded = pipeline.load_pipeline(DEFAULT_MODEL_DIR)
  arguments, noise, setup = sheet_sampling(loaded, batch, winograd)
  start = time.perf_counter()
  compiled = sampler.program(loaded.models).lower(*arguments, noise(0), setup.guidance,
                                                  settings=setup.settings).compile()
  compile_seconds = time.perf_counter() - start
  call_seconds = []
  for seed in range(4):
    start = time.perf_counter()
    compiled(*arguments, noise(seed), setup.guidance).block_until_ready()
    call_seconds.append(time.perf_counter() - start)
  return {"batch": batch, "winograd_convolutions": winograd,
          "compile_seconds": round(compile_seconds, 2),
          "first_call_seconds": round(call_seconds[0], 2),
          "later_call_seconds": round(statistics.median(call_seconds[1:]), 2),
          "algorithms": dict(algorithms),
          "kernel_transforms_called_from": kernel_transforms_by_place(compiled.as_text())}


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--repeats", type=int, default=2, help="processes per setting")
  parser.add_argument("--name", default="bench_winograd_compile")
  parser.add_argument("--child", nargs=2, type=int, metavar=("BATCH", "WINOGRAD"),
                      help=argparse.SUPPRESS)
  results_dir.add_argument(parser)
  args = parser.parse_args()
  if args.child:
    print(json.dumps(measure(args.child[0], bool(args.child[1]))))
    return
  record = {"what": __doc__.split("\n\n")[2].replace("\n", " "),
            "machine": machine.record(), "runs": []}
  for _ in range(args.repeats):
    for batch in (1, 4):
      for winograd in (0, 1):
        output = subprocess.run(
            [sys.executable, __file__, "--child", str(batch), str(winograd)], check=True,
            capture_output=True, text=True, env={**os.environ, "JAX_ENABLE_COMPILATION_CACHE": "0"}).stdout
        record["runs"].append(json.loads(output.splitlines()[-1]))
        print(record["runs"][-1], flush=True)
  record["median"] = {
      f"batch {batch}, winograd {bool(winograd)}": {
          field: statistics.median(run[field] for run in record["runs"]
                                   if (run["batch"], run["winograd_convolutions"])
                                   == (batch, bool(winograd)))
          for field in ("compile_seconds", "first_call_seconds", "later_call_seconds")}
      for batch in (1, 4) for winograd in (0, 1)}
  record["machine"]["load_average_at_end"] = os.getloadavg()
  files.write_json(args.results / f"{args.name}.json", record)
  print(json.dumps(record["median"], indent=1))


if __name__ == "__main__":
  main()
