"""One entry point for every dataset format: detect it, read it, normalise it."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

from signerf_jax.data import blender, llff, nerfstudio
from signerf_jax.data.dataset import SCENE_KINDS, Dataset
from signerf_jax.errors import InputError

# The file that identifies each format, in the order they are tried.
FORMAT_MARKERS = {
    "nerfstudio": nerfstudio.TRANSFORMS_NAME,
    "blender": "transforms_train.json",
    "llff": llff.POSES_NAME,
}


def detect_format(root: str | os.PathLike) -> str:
  """"nerfstudio", "blender" or "llff", from the files in `root`."""
  root = Path(root)
  if not root.is_dir():
    raise InputError("dataset directory not found", root)
  for name, marker in FORMAT_MARKERS.items():
    if (root / marker).is_file():
      return name
  raise InputError(f"unknown dataset format: none of {list(FORMAT_MARKERS.values())} found",
                   root)


def load_dataset(root: str | os.PathLike, *, split: str = "train", downscale: int = 1,
                 background_color=(1.0, 1.0, 1.0), eval_every: int = 8,
                 scene_kind: str | None = None) -> Dataset:
  """Reads a nerfstudio, Blender or LLFF dataset into the normalised scene frame.

  Args:
    root: the dataset directory.
    split: "train", "eval" or "all". Blender uses its own files (train / test); the others hold
      out every `eval_every`-th view, starting with the first.
    downscale: integer image downscale; images_N/ folders are used where the source has them,
      otherwise images are area-resampled. Intrinsics follow `Cameras.downscaled`.
    background_color: [3] RGB that RGBA images are composited on (Blender, RGBA nerfstudio).
    eval_every: the hold-out period for formats without split files.
    scene_kind: overrides the kind the reader infers (the normalisation stays the same; a
      scene made "bounded" gets `background_color` as its background).
  Returns:
    A Dataset whose content lies inside [-1, 1]^3; `world_from_source` maps the source's frame
    into it. Train and eval splits of one source share that frame.
  Raises:
    InputError: naming the file and field at fault.
  """
  if isinstance(downscale, bool) or not isinstance(downscale, int) or downscale < 1:
    raise InputError(f"must be a positive integer, got {downscale!r}", field="downscale")
  if scene_kind is not None and scene_kind not in SCENE_KINDS:
    raise InputError(f"must be one of {SCENE_KINDS}, got {scene_kind!r}", field="scene_kind")
  source_format = detect_format(root)
  if source_format == "nerfstudio":
    dataset = nerfstudio.read_nerfstudio(root, split=split, downscale=downscale,
                                         background_color=background_color,
                                         eval_every=eval_every)
  elif source_format == "blender":
    dataset = blender.read_blender(root, split=split, downscale=downscale,
                                   background_color=background_color)
  else:
    dataset = llff.read_llff(root, split=split, downscale=downscale, eval_every=eval_every)
  if scene_kind is not None and scene_kind != dataset.scene_kind:
    # Only bounded scenes have a constant background colour.
    background = np.asarray(background_color, np.float32) if scene_kind == "bounded" else None
    dataset = dataclasses.replace(dataset, scene_kind=scene_kind, background_color=background)
  return dataset
