"""`signerf edit`: the whole SIGNeRF pipeline, from the original NeRF to the evaluation."""

from __future__ import annotations

import argparse

from signerf_jax.editing.commands import add_edit_arguments, run_stages


def add_arguments(parser: argparse.ArgumentParser) -> None:
  add_edit_arguments(parser)


def run(args: argparse.Namespace) -> int:
  edit, seconds = run_stages("edit", args)
  final = 2 if edit.config.second_iteration else 1
  path = edit.directory.path
  print(f"signerf edit: done in {seconds:.0f} s; sheet "
        f"{path('sheet', 'sheet.png', iteration=final)}, edited dataset "
        f"{path('dataset', iteration=final)}, edited NeRF {path('edited', iteration=final)}, "
        f"metrics {path('evaluation', 'metrics.json')}")
  return 0
