"""`signerf synthesize`: write a synthetic scene with ground truth in nerfstudio format, and the
gin bindings it was made with (config.gin) beside it."""

from __future__ import annotations

import argparse
import time

from signerf_jax import cli, configs, ownership
from signerf_jax.data import synthetic, synthetic_render
from signerf_jax.validation import NonNegativeInt, argument_type


def add_arguments(parser: argparse.ArgumentParser) -> None:
  cli.add_output_argument(parser, "--out", required=True,
                          help="directory to write the dataset to: new, empty, or a dataset "
                          "`signerf synthesize` wrote (never a folder of other files)")
  configs.add_gin_arguments(parser, "synthetic_cameras.image_size = 128")
  parser.add_argument("--seed", type=argument_type(NonNegativeInt), default=0,
                      help="random seed of the scene")


def run(args: argparse.Namespace) -> int:
  configs.parse_gin(args.gin_file, args.gin_param)
  start = time.perf_counter()
  settings, rig = configs.build(synthetic.SceneSettings), configs.build(synthetic_render.CameraRig)
  with ownership.claimed(args.out, ownership.DATASET):
    dataset, scene = synthetic_render.generate(args.out, seed=args.seed, settings=settings,
                                               rig=rig)
    configs.save_gin_config(args.out)
  seconds = time.perf_counter() - start
  print(f"signerf synthesize: {dataset.num_images} views of {dataset.width}x{dataset.height} px, "
        f"{len(scene.objects)} objects (seed {args.seed}) written to {args.out} in "
        f"{seconds:.1f} s")
  return 0
