"""`signerf synthesize`: write a synthetic scene with ground truth in nerfstudio format."""

from __future__ import annotations

import argparse
import time

from signerf_jax import configs
from signerf_jax.data import synthetic


def add_arguments(parser: argparse.ArgumentParser) -> None:
  parser.add_argument("--out", required=True, help="directory to write the dataset to")
  configs.add_gin_arguments(parser, "synthetic_cameras.image_size = 128")
  parser.add_argument("--seed", type=int, default=0, help="random seed of the scene")


def run(args: argparse.Namespace) -> int:
  configs.parse_gin(args.gin_file, args.gin_param)
  start = time.perf_counter()
  dataset, scene = synthetic.generate(args.out, seed=args.seed)
  seconds = time.perf_counter() - start
  print(f"signerf synthesize: {dataset.num_images} views of {dataset.width}x{dataset.height} px, "
        f"{len(scene.objects)} objects (seed {args.seed}) written to {args.out} in "
        f"{seconds:.1f} s")
  return 0
