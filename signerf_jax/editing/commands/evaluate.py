"""`signerf eval`: a trained NeRF's metrics (`nerf.commands.evaluate`) or, with --edit, an
edit's (background preservation, consistency, CLIP), as one JSON line."""

from __future__ import annotations

import argparse

from signerf_jax import ownership
from signerf_jax.editing import commands
from signerf_jax.nerf.commands import evaluate as nerf_evaluate


def add_arguments(parser: argparse.ArgumentParser) -> None:
  target = parser.add_mutually_exclusive_group(required=True)
  target.add_argument("--run", help=nerf_evaluate.RUN_HELP)
  target.add_argument("--edit", help="the edit directory (`signerf place`, `preview` or `edit`): "
                      "evaluate the edit instead, running any unfinished stage first "
                      "(background preservation, consistency, CLIP)")
  nerf_evaluate.add_options(parser)


def run(args: argparse.Namespace) -> int:
  if args.edit is not None:
    return commands.run_evaluation(args.edit)
  # The evaluation writes eval.json and eval/ into the run: only into a run signerf made.
  with ownership.claimed(args.run, ownership.RUN, flag="run"):
    return nerf_evaluate.run(args)
