"""The NeRF's `signerf` subcommands (train, render, eval): one module each, sharing these helpers."""

from __future__ import annotations

import argparse
from typing import Any

from signerf_jax.data import Dataset, load_dataset
from signerf_jax.errors import InputError


def add_gin_arguments(parser: argparse.ArgumentParser) -> None:
  parser.add_argument("--gin_file", action="append", default=[],
                      help="gin file (path or name in gin_configs/); repeatable")
  parser.add_argument("--gin_param", action="append", default=[],
                      help="gin binding such as 'TrainConfig.steps = 2000'; repeatable")


def load_recorded_dataset(description: dict[str, Any], split: str) -> Dataset:
  """The dataset a run was trained on (as model.json recorded it), in another split."""
  options = dict(description.get("data_options") or {})
  if "root" not in options:
    raise InputError("the run does not record where its data came from", None, "data_options")
  root = options.pop("root")
  return load_dataset(root, split=split, **options)
