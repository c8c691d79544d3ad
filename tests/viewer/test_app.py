"""The viewer's server without a browser: what it starts from, what its handle and panel change,
standing the proxy on the NeRF's surface, and what it saves."""

from __future__ import annotations

import dataclasses
import shutil
import types

import numpy as np
import pytest

from signerf_jax import configs
from signerf_jax.editing import place
from signerf_jax.editing.commands import parse_edit_config
from signerf_jax.editing.config import SelectionConfig
from signerf_jax.viewer import app

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def edit_copy(viewed_edit, tmp_path_factory):
  """The edit directory, copied: this module saves into it."""
  directory = tmp_path_factory.mktemp("edit_copy")
  shutil.copytree(viewed_edit, directory, dirs_exist_ok=True)  # With signerf's record of it.
  return directory


@pytest.fixture(scope="module")
def viewer(viewed_run, edit_copy):
  served = app.Viewer(viewed_run[0], edit_copy, port=8094, heights=(16,))
  yield served
  served.close()


def test_the_viewer_starts_from_the_edits_saved_selection_and_prompt(viewer, viewed_run):
  _, scene = viewed_run
  assert viewer.selection.proxy == "primitive:cow"
  np.testing.assert_allclose(viewer.selection.ground_position, scene["free_spot"]["center"])
  assert viewer.prompt_field.value == "a red cow"
  assert viewer.position_field.value == pytest.approx(viewer.selection.ground_position)
  assert len(viewer.camera_frustums) == viewer.dataset.num_images


def test_without_a_saved_selection_a_proxy_stands_at_the_scene_centre(viewed_run, tmp_path):
  fresh = app.Viewer(viewed_run[0], tmp_path / "new_edit", port=8095, heights=(16,))
  try:
    selection = fresh.selection
    assert selection.kind == "proxy" and selection.proxy == "primitive:box"
    _, centre = place.handle_pose(selection, fresh.dataset)
    np.testing.assert_allclose(centre, 0.0, atol=1e-5)  # The scene frame's origin.
    assert selection.ground_size > 0
    assert fresh.prompt_field.value == ""
  finally:
    fresh.close()


def test_a_handle_dragged_and_released_moves_the_selection(viewer):
  before = viewer.selection
  rotation, position = place.handle_pose(before, viewer.dataset)
  viewer.handle.position = position + np.array([0.02, 0.0, 0.0])
  viewer.handle_moved(types.SimpleNamespace(phase="update"))
  assert viewer.selection == before  # Only a release moves the selection.
  viewer.handle_moved(types.SimpleNamespace(phase="end"))
  _, moved = place.handle_pose(viewer.selection, viewer.dataset)
  np.testing.assert_allclose(moved, position + [0.02, 0.0, 0.0], atol=1e-5)
  viewer.selection = before
  viewer.show_selection()


def test_standing_on_the_surface_puts_a_floating_proxy_on_the_ground(viewer, viewed_run):
  _, scene = viewed_run
  before = viewer.selection
  ground = np.asarray(scene["free_spot"]["center"], np.float64)
  up = np.asarray(scene["up"], np.float64)
  viewer.selection = dataclasses.replace(before, ground_position=tuple(ground + 0.15 * up))
  try:
    viewer.stand_on_surface()
    landed = np.asarray(viewer.selection.ground_position)
    # The small NeRF's ground is rough: within 0.05 of the true one (the proxy was 0.15 above),
    # its normal within 30 degrees of up.
    assert abs(np.dot(landed - ground, up)) < 0.05, landed
    assert np.dot(viewer.selection.up, up) > np.cos(np.deg2rad(30))
    assert viewer.selection.ground_size == pytest.approx(before.ground_size)
  finally:
    viewer.selection = before
    viewer.show_selection()


def test_a_reroll_previews_the_sheet_with_those_tiles_generated_again(viewer, edit_copy):
  viewer.reroll_tiles.value = "1"
  viewer.reroll_seed.value = 7
  paths = viewer.submit(viewer.reroll).result()
  assert viewer.recipes == ("0/1@7",)  # Sheet 0 (the edit's seed) with tile 1 from seed 7.
  assert len(paths) == 3 and all(path.is_file() for path in paths)
  assert viewer.sheet_field.options == ("0", "1", "0/1@7")
  assert len(viewer.candidates) == 3
  viewer.reroll_tiles.value = "one"
  assert viewer.submit(viewer.reroll).result() is None
  assert "error" in viewer.status.content and viewer.recipes == ("0/1@7",)


def test_save_leaves_the_users_files_in_the_edit_as_they_were(viewer, edit_copy):
  names = (".env.database", "notes/.tool.settings.json", "selection/my_selection.json",
           "reference/paper.pdf", ".config.a1b2c3d4.gin")
  for name in names:
    (edit_copy / name).parent.mkdir(parents=True, exist_ok=True)
    (edit_copy / name).write_text(f"the user's {name}")
  viewer.submit(viewer.save).result()
  for name in names:
    assert (edit_copy / name).read_text() == f"the user's {name}"


def test_save_writes_the_selection_and_settings_that_the_edit_reads(viewer, edit_copy):
  viewer.seed_field.value = 5
  viewer.controlnet_field.value = 0.5
  viewer.submit(viewer.save).result()
  parse_edit_config(edit_copy, (), ())
  assert configs.build(SelectionConfig) == viewer.selection
  text = (edit_copy / "config.gin").read_text()
  assert "EditConfig.seed = 5" in text
  assert "controlnet_conditioning_scale = 0.5" in text
