"""`signerf preview`: candidate reference sheets side by side, and per-tile re-rolls."""

from __future__ import annotations

import argparse

from signerf_jax.editing.commands import add_edit_arguments, gin_value, run_stages
from signerf_jax.editing.config import PreviewConfig
from signerf_jax.validation import argument_type


def add_arguments(parser: argparse.ArgumentParser) -> None:
  add_edit_arguments(parser, "preview")
  parser.add_argument("--seeds", type=argument_type(PreviewConfig, "seeds"), nargs="+",
                      help="one candidate sheet per seed (default: "
                      f"{' '.join(map(str, PreviewConfig.seeds))})")
  parser.add_argument("--reroll", nargs="+", metavar="RECIPE",
                      help="re-rolled candidates, e.g. 2/1,4@7: sheet 2 with tiles 1 and 4 "
                      "generated again with seed 7, the other tiles kept (default: none)")


def run(args: argparse.Namespace) -> int:
  bindings = []
  if args.seeds is not None:
    bindings.append(f"PreviewConfig.seeds = {gin_value(args.seeds)}")
  if args.reroll is not None:
    bindings.append(f"PreviewConfig.recipes = {gin_value(args.reroll)}")
  edit, seconds = run_stages("preview", args, bindings)
  print(f"signerf preview: candidates in {edit.directory.path('preview', 'candidates')}, side "
        f"by side in {edit.directory.path('preview', 'preview.png')} ({seconds:.0f} s)")
  return 0
