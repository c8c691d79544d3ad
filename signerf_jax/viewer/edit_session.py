"""The edit the viewer works on: its context built from the edit directory's saved config.gin
(or placeholders where it has none yet) and the selection it starts from."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from signerf_jax import configs
from signerf_jax.data import poses as poses_lib
from signerf_jax.editing import stages
from signerf_jax.editing.commands import edit_settings, gin_value, parse_edit_config
from signerf_jax.editing.config import EditConfig, SelectionConfig
from signerf_jax.editing.project import EditDirectory
from signerf_jax.errors import InputError
from signerf_jax.nerf.commands import info

# Bound only to build the edit's context when the edit has none yet (the panel shows the real
# values, and the pipeline asks for them when they are missing).
PLACEHOLDER_PROMPT = "EditConfig.prompt = 'not set'"


def load(run_dir: Path, edit_dir: Path, default_proxy: str
         ) -> tuple[stages.EditContext, SelectionConfig | None, str]:
  """(context of the edit, its saved selection or None, its saved prompt or "")."""
  base = [f"EditConfig.original_run = {gin_value(str(run_dir.resolve()))}"]
  parse_edit_config(edit_dir, (), base)
  try:
    selection = configs.build(SelectionConfig)
  except InputError:
    selection = None
  try:
    prompt = configs.build(EditConfig).prompt
  except InputError:
    prompt = ""
  placeholders = [] if prompt else [PLACEHOLDER_PROMPT]
  if selection is None:
    placeholders += ["SelectionConfig.kind = 'proxy'",
                     f"SelectionConfig.proxy = {gin_value(default_proxy)}",
                     "SelectionConfig.ground_position = (0.0, 0.0, 0.0)"]
  parse_edit_config(edit_dir, (), base + placeholders)
  return stages.EditContext(EditDirectory(edit_dir), edit_settings(), progress=False), \
      selection, prompt


def default_selection(dataset, proxy: str) -> SelectionConfig:
  """A proxy of `info.default_proxy_size` (a tenth of the cameras' distance from the centre
  where the dataset records no frame) standing at the scene frame's centre, in the dataset's
  own units: the start when the edit has no selection yet."""
  world_from_source = np.asarray(dataset.world_from_source, np.float64)
  centre = poses_lib.transform_points(np.linalg.inv(world_from_source), np.zeros(3))
  size = info.default_proxy_size(dataset)
  if not np.isfinite(size):
    distance = np.median(np.linalg.norm(np.asarray(dataset.cameras.positions), axis=1))
    size = round(float(0.1 * distance / poses_lib.similarity_scale(world_from_source)), 6)
  return SelectionConfig(kind="proxy", proxy=proxy, frame="source",
                         ground_position=tuple(round(float(value), 6) for value in centre),
                         ground_size=size)
