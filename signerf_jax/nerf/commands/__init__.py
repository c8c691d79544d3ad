"""The NeRF's `signerf` subcommands (train, render, eval): one module each, sharing these helpers."""

from __future__ import annotations

import argparse
import dataclasses
import typing
from pathlib import Path
from typing import Annotated, Any

from signerf_jax import validation
from signerf_jax.data import Dataset, load_dataset
from signerf_jax.data.frame import SceneKind
from signerf_jax.errors import InputError
from signerf_jax.validation import PositiveFloat, PositiveInt, Range, Vector3, argument_type


@dataclasses.dataclass(frozen=True)
class DataConfig(validation.CheckedFields):
  """How a dataset is read: the options of `data.load_dataset` besides the split (gin:
  `DataConfig.<field>`; each has a command-line flag of the same name, which wins over gin). A
  run records them in model.json, so its held-out split loads in the same frame.

  Attributes:
    downscale: integer image downscale.
    eval_every: hold out every N-th view instead of the dataset's own split.
    held_out: names of the views to hold out (wins over everything else).
    scene_kind: "bounded", "forward_facing" or "unbounded" instead of what the data suggests.
    scene_center: (x, y, z) centre of the region modelled in detail, in the dataset's units.
    scene_radius: half-side of that region, in the dataset's units.
  """

  downscale: PositiveInt = 1
  eval_every: Annotated[int, Range(2)] | None = None
  held_out: tuple[str, ...] = ()
  scene_kind: SceneKind | None = None
  scene_center: Vector3 | None = None
  scene_radius: PositiveFloat | None = None


def add_data_arguments(parser: argparse.ArgumentParser) -> None:
  """Flags for every `DataConfig` field (default: the gin-bound value)."""
  parser.add_argument("--downscale", type=argument_type(DataConfig, "downscale"), default=None,
                      help="integer image downscale (default: the gin-bound "
                      f"DataConfig.downscale, {DataConfig.downscale})")
  parser.add_argument("--eval_every", type=argument_type(DataConfig, "eval_every"), default=None,
                      help="hold out every N-th view (default: the dataset's own split, else 8)")
  parser.add_argument("--held_out", default=None,
                      help="views to hold out: comma-separated names, or @FILE with one per line "
                      "(default: as --eval_every)")
  parser.add_argument("--scene_kind", default=None,
                      choices=typing.get_args(SceneKind),
                      help="override the scene kind (default: the one the data suggests)")
  parser.add_argument("--scene_center", type=argument_type(DataConfig, "scene_center"), nargs=3,
                      default=None, metavar=("X", "Y", "Z"),
                      help="centre of the region modelled in detail, in the dataset's units "
                      "(default: found from the cameras and SfM points)")
  parser.add_argument("--scene_radius", type=argument_type(DataConfig, "scene_radius"),
                      default=None, help="half-side of that region, in the dataset's units "
                      "(default: found from the cameras)")


def _held_out_names(value: str) -> tuple[str, ...]:
  if value.startswith("@"):
    path = Path(value[1:])
    if not path.is_file():
      raise InputError("held-out list not found", path, "held_out")
    lines = path.read_text(encoding="utf-8").splitlines()
  else:
    lines = value.split(",")
  return tuple(line.strip() for line in lines if line.strip())


def data_options(args: argparse.Namespace, config: DataConfig) -> dict[str, Any]:
  """`load_dataset`'s options (JSON-friendly): `config` (the gin-bound one) with the given flags
  on top, and the dataset's absolute root."""
  flags = {name: getattr(args, name) for name in ("downscale", "eval_every", "scene_kind",
                                                  "scene_radius")
           if getattr(args, name, None) is not None}
  if getattr(args, "held_out", None) is not None:
    flags["held_out"] = _held_out_names(args.held_out)
  if getattr(args, "scene_center", None) is not None:
    flags["scene_center"] = tuple(args.scene_center)
  options = dataclasses.asdict(dataclasses.replace(config, **flags))
  options["held_out"] = list(options["held_out"])
  return {"root": str(Path(args.data).resolve()), **options}


def load_recorded_dataset(description: dict[str, Any], split: str) -> Dataset:
  """The dataset a run was trained on (as model.json recorded it), in another split."""
  options = dict(description.get("data_options") or {})
  if "root" not in options:
    raise InputError("the run does not record where its data came from", None, "data_options")
  root = options.pop("root")
  options["held_out"] = tuple(options.get("held_out") or ())
  return load_dataset(root, split=split, **options)
