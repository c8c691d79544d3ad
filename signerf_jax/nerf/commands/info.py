"""`signerf info`: what a trained run's scene looks like in the dataset's own units — the frame
it was normalised into, the region modelled in detail, the cameras, the training views (the
indices `signerf place --view` takes) and a sensible proxy size. Human-readable lines on stderr,
one JSON line on stdout."""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from signerf_jax.data import frame as frame_lib
from signerf_jax.data import poses as poses_lib
from signerf_jax.geometry import reference_cameras
from signerf_jax.nerf import training_run
from signerf_jax.nerf.commands import load_recorded_dataset

# The default proxy size: this fraction of the region modelled in detail (its mean side).
DEFAULT_SIZE_FRACTION_OF_REGION = 0.2
LISTED_VIEWS = 12


def add_arguments(parser: argparse.ArgumentParser) -> None:
  parser.add_argument("--run", required=True, help="run directory written by `signerf train`")


def default_proxy_size(dataset) -> float:
  """A proxy size that suits the scene, in the dataset's own units: a fifth of the region
  modelled in detail (NaN where the dataset records no frame)."""
  half_size = np.asarray((dataset.frame or {}).get("half_size_in_source_units", [np.nan] * 3))
  return round(float(DEFAULT_SIZE_FRACTION_OF_REGION * 2 * half_size.mean()), 6)


def describe(run_dir) -> dict:
  """The run's scene in the dataset's own units (JSON-friendly)."""
  _, description = training_run.read_model_file(run_dir)
  dataset = load_recorded_dataset(description, "train")
  source_from_world = np.linalg.inv(np.asarray(dataset.world_from_source, np.float64))
  positions = poses_lib.transform_points(source_from_world,
                                         np.asarray(dataset.cameras.positions, np.float64))
  up = source_from_world[:3, :3] @ reference_cameras.scene_up(dataset.cameras)
  frame = dataset.frame or {}
  return {
      "frame": frame,
      "views": {"count": dataset.num_images, "width": dataset.width, "height": dataset.height,
                "names": list(dataset.image_names)},
      "camera_positions": {"min": positions.min(0).round(6).tolist(),
                           "max": positions.max(0).round(6).tolist()},
      "up": (up / np.linalg.norm(up)).round(6).tolist(),
      "default_proxy_size": default_proxy_size(dataset),
      "units": "the dataset's own",
  }


def run(args: argparse.Namespace) -> int:
  info = describe(args.run)
  views = info["views"]
  listed = ", ".join(f"{index}: {name}" for index, name in enumerate(views["names"][:LISTED_VIEWS]))
  more = f", ... ({views['count'] - LISTED_VIEWS} more)" if views["count"] > LISTED_VIEWS else ""
  lines = [frame_lib.summary_line(info["frame"]) if info["frame"] else "scene frame: not recorded",
           f"{views['count']} training views of {views['width']}x{views['height']} px "
           f"(`signerf place --view` takes the index or the name): {listed}{more}",
           f"cameras between {info['camera_positions']['min']} and "
           f"{info['camera_positions']['max']}; up {info['up']}",
           f"a proxy of about {info['default_proxy_size']:g} (a fifth of the region) fits: "
           f"`signerf place --size {info['default_proxy_size']:g}`"]
  for line in lines:
    print(f"signerf info: {line}", file=sys.stderr)
  print(json.dumps(info))
  return 0
