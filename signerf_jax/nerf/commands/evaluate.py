"""`signerf eval`: metrics of a trained run on its held-out views, as one JSON line."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from signerf_jax import files
from signerf_jax.nerf import evaluate
from signerf_jax.nerf.commands import load_recorded_dataset

EVAL_FILE = "eval.json"


def add_arguments(parser: argparse.ArgumentParser) -> None:
  target = parser.add_mutually_exclusive_group(required=True)
  target.add_argument("--run", help="run directory written by `signerf train`")
  target.add_argument("--edit", help="edit directory written by `signerf edit`: evaluate the "
                      "edit instead (background preservation, consistency, CLIP)")
  parser.add_argument("--split", default="eval", choices=("train", "eval", "all"),
                      help="which dataset views to evaluate on")
  parser.add_argument("--chunk_size", type=int, default=4096, help="rays rendered at once")


def run(args: argparse.Namespace) -> int:
  if args.edit is not None:
    from signerf_jax.editing import commands  # pylint: disable=g-import-not-at-top
    return commands.run_evaluation(args.edit)
  trained = evaluate.load_run(args.run)
  dataset = load_recorded_dataset(trained.description, args.split)
  metrics, _ = evaluate.evaluate(trained.model, trained.variables, dataset, args.chunk_size)
  result = {**metrics, "seconds_trained": trained.seconds_trained, "step": trained.step,
            "split": args.split}
  files.write_json(Path(args.run) / EVAL_FILE, result)
  print(json.dumps(result))
  return 0
