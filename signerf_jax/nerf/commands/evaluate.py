"""`signerf eval`: metrics of a trained run on its held-out views, as one JSON line."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Any

from signerf_jax import files
from signerf_jax.errors import InputError
from signerf_jax.metrics import lpips
from signerf_jax.nerf import evaluate, render
from signerf_jax.nerf.commands import load_recorded_dataset
from signerf_jax.validation import PositiveInt, argument_type

EVAL_FILE = "eval.json"
RENDERS_FOLDER = "eval"
RUN_HELP = "run directory written by `signerf train`"


def add_arguments(parser: argparse.ArgumentParser) -> None:
  parser.add_argument("--run", required=True, help=RUN_HELP)
  add_options(parser)


def add_options(parser: argparse.ArgumentParser) -> None:
  """The options besides the run directory (`signerf eval` adds --edit beside --run)."""
  parser.add_argument("--split", default="eval", choices=("train", "eval", "all"),
                      help="views to evaluate; eval (the held-out views) also reports the "
                      "training views' PSNR and the gap")
  parser.add_argument("--lpips", default="",
                      help="VGG-LPIPS weights (safetensors) for LPIPS (default: none, no LPIPS)")
  parser.add_argument("--chunk_size", type=argument_type(PositiveInt),
                      default=render.DEFAULT_CHUNK_SIZE, help="rays rendered at once")
  add_supersampling(parser)


def add_supersampling(parser: argparse.ArgumentParser) -> None:
  """--supersampling, shared by `signerf eval` and `signerf render`."""
  parser.add_argument("--supersampling", type=argument_type(PositiveInt), default=None,
                      help="render each pixel as the mean of N x N rays inside it "
                      "(anti-aliasing, N^2 times the rendering time); 1: one ray through its "
                      "centre; default: as the model was trained (its pixel_samples)")


def evaluate_run(run_dir: str | os.PathLike, split: str = "eval", lpips_weights: str = "",
                 chunk_size: int = render.DEFAULT_CHUNK_SIZE, supersampling: int | None = None
                 ) -> dict[str, Any]:
  """Evaluates a run on `split`; writes RUN/eval.json and, for the held-out split, the renders
  and depth maps to RUN/eval/. Returns what eval.json holds.

  Raises:
    InputError: among others, a chunk size whose buffers cannot fit in memory (naming
      --chunk_size; checked before anything is loaded).
  """
  render.check_chunk_size(chunk_size, "--chunk_size")
  run_dir = Path(run_dir)
  trained = evaluate.load_run(run_dir)
  lpips_params = None
  if lpips_weights:
    if not Path(lpips_weights).is_file():
      raise InputError("LPIPS weights file not found", lpips_weights, "lpips")
    lpips_params = lpips.load_lpips_params(lpips_weights)
  dataset = load_recorded_dataset(trained.description, split)
  if split == "eval":
    result, _ = evaluate.generalisation_report(
        trained.model, trained.variables, dataset, load_recorded_dataset(
            trained.description, "train"), chunk_size, lpips_params, run_dir / RENDERS_FOLDER,
        supersampling)
  else:
    result, _ = evaluate.evaluate(trained.model, trained.variables, dataset, chunk_size,
                                  lpips_params, supersampling=supersampling)
  result = {**result, "seconds_trained": trained.seconds_trained, "step": trained.step,
            "split": split}
  files.write_json(run_dir / EVAL_FILE, result)
  return result


def run(args: argparse.Namespace) -> int:
  print(json.dumps(evaluate_run(args.run, args.split, args.lpips, args.chunk_size,
                                args.supersampling)))
  return 0
