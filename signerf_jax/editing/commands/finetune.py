"""`signerf finetune`: the NeRF fine-tuned (or retrained) on the edited dataset."""

from __future__ import annotations

import argparse

from signerf_jax.editing.commands import add_edit_arguments, run_stages


def add_arguments(parser: argparse.ArgumentParser) -> None:
  add_edit_arguments(parser)


def run(args: argparse.Namespace) -> int:
  edit, seconds = run_stages("finetune", args)
  print(f"signerf finetune: edited NeRF in {edit.directory.path('edited')} "
        f"({seconds:.0f} s)")
  return 0
