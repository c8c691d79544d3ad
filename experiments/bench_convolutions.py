"""Each way to compute a 3x3 convolution, timed on the layer shapes of SD 1.5's UNet and VAE.

  python experiments/bench_convolutions.py [--repeats 5] [--name bench_convolutions]

For every shape (batch, height, width, in channels, out channels) it compiles and times XLA's own
convolution, the im2col matmul, Winograd's F(2x2, 3x3) and F(4x4, 3x3) (float32), and reports
which one `layers.conv2d` picks on a CPU (`layers.cpu_convolution_algorithm`), each one's
compilation seconds and its largest difference from XLA's result relative to that result's
largest magnitude. The algorithms run in turn, repeat
after repeat, so a change of load slows them alike; the best of the repeats is reported.
Writes NAME.json with the machine and load into --results DIR (default outputs/experiments/).
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

import machine
import results_dir
from signerf_jax import files
from signerf_jax.diffusion import layers

# (name, batch, height, width, in channels, out channels): the UNet's levels at a 64x64 and a
# 32x32 latent with classifier-free guidance's batch of 2 (first resnet convolutions, and the up
# path's concatenated inputs), and the VAE decoder's levels decoding one 512x512 image.
SHAPES = (
    ("unet 64x64 level", 2, 64, 64, 320, 320),
    ("unet 64x64 up, concatenated", 2, 64, 64, 960, 320),
    ("unet 32x32 level", 2, 32, 32, 640, 640),
    ("unet 16x16 level", 2, 16, 16, 1280, 1280),
    ("vae decoder 128x128", 1, 128, 128, 512, 512),
    ("vae decoder 256x256", 1, 256, 256, 256, 256),
    ("vae decoder 512x512", 1, 512, 512, 128, 128),
)

ALGORITHMS = {
    "xla": lambda x, kernel: layers.xla_conv(x, kernel, 1, 1, jnp.float32),
    "im2col": lambda x, kernel: layers.im2col_conv(x, kernel, 1, 1, jnp.float32),
    "winograd_2x2": lambda x, kernel: layers.winograd_2x2_conv3x3(x, kernel, jnp.float32),
    "winograd_4x4": lambda x, kernel: layers.winograd_4x4_conv3x3(x, kernel, jnp.float32),
}


def measure(shape: tuple[int, ...], repeats: int) -> dict:
  """Times, compilation times and errors of every algorithm for one (B, H, W, C, O) shape."""
  batch, height, width, channels, out = shape
  x = jax.random.normal(jax.random.key(0), (batch, height, width, channels))
  kernel = jax.random.normal(jax.random.key(1), (3, 3, channels, out)) / np.sqrt(9 * channels)
  compiled, compile_seconds = {}, {}
  for name, function in ALGORITHMS.items():
    start = time.perf_counter()
    compiled[name] = jax.jit(function).lower(x, kernel).compile()
    compile_seconds[name] = time.perf_counter() - start
  reference = np.asarray(compiled["xla"](x, kernel))
  errors = {name: float(np.abs(np.asarray(function(x, kernel)) - reference).max()
                        / np.abs(reference).max()) for name, function in compiled.items()}
  seconds = {name: [] for name in compiled}
  for _ in range(repeats):
    for name, function in compiled.items():
      start = time.perf_counter()
      function(x, kernel).block_until_ready()
      seconds[name].append(time.perf_counter() - start)
  best = {name: min(values) for name, values in seconds.items()}
  chosen = layers.cpu_convolution_algorithm(x.shape, kernel.shape, 1, 1, jnp.float32)
  return {"seconds": best, "compile_seconds": compile_seconds, "relative_error": errors,
          "fastest": min(best, key=best.get), "chosen": chosen,
          "chosen_over_fastest": best[chosen] / min(best.values()),
          "gflop": 2 * batch * height * width * 9 * channels * out / 1e9}


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--repeats", type=int, default=5)
  parser.add_argument("--name", default="bench_convolutions")
  results_dir.add_argument(parser)
  args = parser.parse_args()
  results = {"what": __doc__.splitlines()[0], "date": time.strftime("%Y-%m-%d"),
             "machine": machine.record(), "repeats": args.repeats, "layers": []}
  for name, *shape in SHAPES:
    row = {"layer": name, "shape_bhwco": shape, **measure(tuple(shape), args.repeats)}
    results["layers"].append(row)
    print(name, {key: round(value, 4) for key, value in row["seconds"].items()},
          "chosen", row["chosen"], "fastest", row["fastest"], flush=True)
  results["load_average_at_end"] = os.getloadavg()
  files.write_json(args.results / f"{args.name}.json", results)


if __name__ == "__main__":
  main()
