"""Fixtures of the viewer tests: a tiny trained NeRF and an edit of it with the random-weight
pipeline of the editing tests."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from signerf_jax import cli, files, ownership
from signerf_jax.data import synthetic, synthetic_render

# The helpers of the editing and NeRF tests: random_pipeline, small_nerf.
sys.path[:0] = [str(Path(__file__).parents[1] / folder) for folder in ("editing", "nerf")]
from random_pipeline import write_random_pipeline  # pylint: disable=wrong-import-position


@pytest.fixture(scope="session")
def viewed_run(tmp_path_factory):
  """(run directory, scene description): a NeRF trained briefly on a 40 px, 12-view scene (200
  steps: enough for a ground solid enough to stand a proxy on; a quarter of the default sample
  budget, 2,048 rays a step, trains in a third of the time to within 0.5 dB)."""
  directory = tmp_path_factory.mktemp("viewed")
  _, scene = synthetic_render.generate(
      directory / "scene", seed=2,
      settings=synthetic.SceneSettings(num_primitives=2, num_meshes=0),
      rig=synthetic_render.CameraRig(num_views=12, image_size=40, field_of_view_degrees=40.0))
  assert cli.main(["train", "--data", str(directory / "scene"), "--run", str(directory / "run"),
                   "--steps", "200", "--gin_param",
                   "CapacityRules.samples_per_batch = 16384"]) == 0
  return directory / "run", files.read_json(directory / "scene" / "scene.json")


@pytest.fixture(scope="session")
def viewed_edit(viewed_run, tmp_path_factory):
  """An edit directory of `viewed_run` whose config.gin sets a prompt, the random pipeline and
  a proxy on the scene's free spot (small sheets, two diffusion steps)."""
  _, scene = viewed_run
  model = write_random_pipeline(tmp_path_factory.mktemp("random_model"))
  directory = tmp_path_factory.mktemp("edit")
  free_spot = scene["free_spot"]
  with ownership.claimed(directory, ownership.EDIT):  # As `signerf place` writes it.
    files.write_text(directory / "config.gin", "\n".join([
        "EditConfig.prompt = 'a red cow'", f"EditConfig.model = {str(model)!r}",
        "SelectionConfig.kind = 'proxy'", "SelectionConfig.proxy = 'primitive:cow'",
        f"SelectionConfig.ground_position = {tuple(free_spot['center'])!r}",
        f"SelectionConfig.ground_size = {min(1.6 * free_spot['radius'], 0.3)!r}",
        f"SelectionConfig.up = {tuple(scene['up'])!r}",
        "SheetConfig.tile_size = 16", "first_iteration/GenerationOptions.num_inference_steps = 2",
        "PreviewConfig.seeds = (0, 1)", ""]))
  return directory
