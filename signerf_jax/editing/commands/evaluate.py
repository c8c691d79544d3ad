"""`signerf eval`: a trained NeRF's metrics (`nerf.commands.evaluate`) or, with --edit, an
edit's (background preservation, adherence; consistency, CLIP and the video when the edit's
gin turns them on, e.g. `--gin_param "EvaluationConfig.independent_views = 12"`), as one JSON
line."""

from __future__ import annotations

import argparse

from signerf_jax import configs, ownership
from signerf_jax.editing import commands
from signerf_jax.errors import InputError
from signerf_jax.nerf.commands import evaluate as nerf_evaluate


def add_arguments(parser: argparse.ArgumentParser) -> None:
  target = parser.add_mutually_exclusive_group(required=True)
  target.add_argument("--run", help=nerf_evaluate.RUN_HELP)
  target.add_argument("--edit", help="the edit directory (`signerf place`, `preview` or `edit`): "
                      "evaluate the edit instead, running any unfinished stage first "
                      "(background preservation, consistency, CLIP)")
  nerf_evaluate.add_options(parser)
  configs.add_gin_arguments(parser, "EvaluationConfig.independent_views = 12")


def check_arguments(args: argparse.Namespace) -> None:
  """Refuses gin with --run: a NeRF's evaluation has no gin settings, an edit's does."""
  if args.run is not None and (args.gin_file or args.gin_param):
    raise InputError("--gin_file and --gin_param set an edit's evaluation: give them with "
                     "--edit", field="gin_param")


def run(args: argparse.Namespace) -> int:
  check_arguments(args)
  if args.edit is not None:
    return commands.run_evaluation(args.edit, args.gin_file, args.gin_param)
  # The evaluation writes eval.json and eval/ into the run: only into a run signerf made.
  with ownership.claimed(args.run, ownership.RUN, flag="run"):
    return nerf_evaluate.run(args)
