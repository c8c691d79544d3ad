"""`signerf update`: the image set update through the chosen sheet, and the edited dataset."""

from __future__ import annotations

import argparse

from signerf_jax.editing.commands import add_edit_arguments, run_stages


def add_arguments(parser: argparse.ArgumentParser) -> None:
  add_edit_arguments(parser)


def run(args: argparse.Namespace) -> int:
  edit, seconds = run_stages("update", args)
  print(f"signerf update: edited views in {edit.directory.path('update', 'images')}, edited "
        f"dataset in {edit.directory.path('dataset')} ({seconds:.0f} s)")
  return 0
