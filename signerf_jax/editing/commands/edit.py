"""`signerf edit`, `signerf update` and `signerf finetune`: the SIGNeRF pipeline up to the
command's last stage (`LAST_STAGE`: evaluate, dataset, finetune), earlier stages first when
they have not run."""

from __future__ import annotations

import argparse

from signerf_jax.editing.commands import add_edit_arguments, run_stages


def add_arguments(parser: argparse.ArgumentParser) -> None:
  add_edit_arguments(parser)  # The flags of the command `parser` is named after.


def run(args: argparse.Namespace) -> int:
  edit, seconds = run_stages(args.command, args)
  # `update` and `finetune` stop in the first iteration (`LAST_STAGE`).
  final = 2 if edit.settings.edit.second_iteration and args.command == "edit" else 1
  path = edit.directory.path
  dataset = f"edited dataset {path('dataset', iteration=final)}"
  nerf = f"edited NeRF {path('edited', iteration=final)}"
  outputs = {
      "edit": (f"sheet {path('sheet', 'sheet.png', iteration=final)}, {dataset}, {nerf}, "
               f"metrics {path('evaluation', 'metrics.json')}"),
      "update": f"edited views {path('update', 'images', iteration=final)}, {dataset}",
      "finetune": nerf,
  }[args.command]
  print(f"signerf {args.command}: done in {seconds:.0f} s; {outputs}")
  return 0
