"""`signerf train`: train (or resume) a NeRF on a dataset directory."""

from __future__ import annotations

import argparse
from pathlib import Path

from signerf_jax import configs
from signerf_jax.data import load_dataset
from signerf_jax.nerf import checkpoint, train
from signerf_jax.nerf.commands import add_gin_arguments


def add_arguments(parser: argparse.ArgumentParser) -> None:
  parser.add_argument("--data", required=True, help="dataset directory (nerfstudio, Blender, LLFF)")
  parser.add_argument("--out", required=True, help="run directory (resumed if it has a checkpoint)")
  parser.add_argument("--downscale", type=int, default=1, help="integer image downscale")
  parser.add_argument("--steps", type=int, default=None, help="overrides TrainConfig.steps")
  parser.add_argument("--max_seconds", type=float, default=None,
                      help="stop after this much training time (resumable)")
  add_gin_arguments(parser)


def run(args: argparse.Namespace) -> int:
  run_dir = Path(args.out)
  saved_config = run_dir / configs.SAVED_CONFIG_NAME
  gin_files = args.gin_file
  # Resuming without new gin files continues with the run's own configuration.
  if not gin_files and checkpoint.has_checkpoint(run_dir) and saved_config.is_file():
    gin_files = [saved_config]
  configs.parse_gin(gin_files, args.gin_param)
  data_options = {"root": str(Path(args.data).resolve()), "downscale": args.downscale}
  dataset = load_dataset(args.data, split="train", downscale=args.downscale)
  trainer = train.train(dataset, run_dir, steps=args.steps, max_seconds=args.max_seconds,
                        data_options=data_options)
  statistics = trainer.last_statistics
  print(f"signerf train: {trainer.step} steps, {trainer.seconds_trained:.0f} s trained, "
        f"last batch {statistics.get('psnr', float('nan')):.2f} dB; run in {run_dir}")
  return 0
