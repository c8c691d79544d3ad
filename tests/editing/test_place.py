"""`signerf place`'s geometry: the support under a picked pixel from what the NeRF renders along
the window's rays, and the selection it gives in the dataset's own units."""

import json
import types

import numpy as np
import pytest

from signerf_jax import camera, cli
from signerf_jax.data.dataset import Dataset
from signerf_jax.editing import place, select
from signerf_jax.editing.commands import place as place_command
from signerf_jax.editing.commands.place import view_index
from signerf_jax.editing.config import SelectionConfig
from signerf_jax.errors import InputError
from signerf_jax.geometry import placement

SIZE = 40
# Source -> scene: scale 0.5, a quarter turn about z, shifted: the printed numbers must be the
# source's, whatever the frame.
WORLD_FROM_SOURCE = np.array([[0.0, -0.5, 0.0, 0.1], [0.5, 0.0, 0.0, -0.2],
                              [0.0, 0.0, 0.5, 0.05], [0.0, 0.0, 0.0, 1.0]])
GROUND_Z = 0.05  # The ground z = 0 of the source frame, in the scene frame.


def ground_dataset() -> Dataset:
  eye = np.array([[1.5, -1.2, 1.0]], np.float32)
  camera_to_world = np.asarray(camera.look_at(eye, np.array([0.1, 0.0, GROUND_Z], np.float32)))
  cameras = camera.Cameras.create(camera_to_world, fx=SIZE * 1.1, width=SIZE, height=SIZE)
  return Dataset(images=np.full((1, SIZE, SIZE, 3), 0.5, np.float32), cameras=cameras,
                 image_names=("images/view.png",),
                 scene_bounds=np.array([[-1, -1, -1], [1, 1, 1]], np.float32),
                 scene_kind="bounded", near=0.1, far=5.0, world_from_source=WORLD_FROM_SOURCE)


def rendered_ground(dataset, pixel, box_pixels=()):
  """What a NeRF of the ground plane renders along the window's rays (median z-depth), with an
  object in front over the window's pixels `box_pixels` (outliers of the fit)."""
  xs, ys = placement.window_pixels(*pixel, SIZE, SIZE, radius=3)
  rays = camera.pixel_rays(dataset.cameras, np.zeros(xs.shape, np.int32), xs, ys)
  origins, directions = np.asarray(rays.origins), np.asarray(rays.directions)
  distance = (GROUND_Z - origins[:, 2]) / directions[:, 2]
  distance[list(box_pixels)] *= 0.7
  return rays, {"accumulation": np.ones(xs.shape, np.float32),
                "median_depth": distance * np.asarray(rays.cos_to_optical_axis)}


def test_the_support_is_the_ground_under_the_pixel_in_the_datasets_units():
  dataset = ground_dataset()
  rays, rendered = rendered_ground(dataset, (21.5, 24.5), box_pixels=range(1, 12))
  found = place.support(dataset, 0, (21.5, 24.5), rays, rendered, size=0.8)
  hit = np.asarray(rays.origins[0]) + np.asarray(rays.directions[0]) * (
      (GROUND_Z - float(rays.origins[0, 2])) / float(rays.directions[0, 2]))
  np.testing.assert_allclose(found.position, hit, atol=1e-4)
  np.testing.assert_allclose(found.up, [0.0, 0.0, 1.0], atol=1e-4)
  selection = found.selection("primitive:box")
  assert selection.frame == "source" and selection.kind == "proxy"
  source_hit = np.linalg.inv(WORLD_FROM_SOURCE) @ np.append(hit, 1.0)
  np.testing.assert_allclose(selection.ground_position, source_hit[:3], atol=1e-4)
  assert selection.ground_position[2] == pytest.approx(0.0, abs=1e-4)
  np.testing.assert_allclose(selection.up, [0.0, 0.0, 1.0], atol=1e-4)
  assert selection.ground_size == pytest.approx(0.8)  # Given in the source's units.
  # The edit stands the proxy exactly there: its lowest point on the ground, under the pixel.
  proxy = select.place_proxy(selection, dataset)
  assert float(np.min(proxy.vertices[:, 2])) == pytest.approx(GROUND_Z, abs=1e-4)
  extent = np.ptp(np.asarray(proxy.vertices, np.float64), axis=0).max()
  assert extent == pytest.approx(0.8 * 0.5, rel=1e-4)  # 0.8 source units = 0.4 scene units.


def test_without_a_size_the_proxy_takes_a_fraction_of_the_views_height():
  dataset = ground_dataset()
  rays, rendered = rendered_ground(dataset, (20.5, 20.5))
  found = place.support(dataset, 0, (20.5, 20.5), rays, rendered, size_fraction=0.25)
  expected = 0.25 * SIZE * float(rendered["median_depth"][0]) / (SIZE * 1.1)
  assert found.size == pytest.approx(expected)


def test_a_pixel_showing_nothing_is_an_error_naming_it():
  dataset = ground_dataset()
  rays, rendered = rendered_ground(dataset, (20.5, 20.5))
  rendered["accumulation"][0] = 0.1
  with pytest.raises(InputError, match="shows no surface") as error:
    place.support(dataset, 0, (20.5, 20.5), rays, rendered)
  assert error.value.field == "pixel"


@pytest.mark.parametrize("view, pixel, field", [(1, (5, 5), "view"), (0, (40, 5), "pixel"),
                                                (0, (5, -1), "pixel")])
def test_a_view_or_pixel_outside_the_dataset_is_refused_before_rendering(view, pixel, field):
  with pytest.raises(InputError) as error:
    place.locate(None, None, ground_dataset(), view, pixel)
  assert error.value.field == field


def test_the_figure_shows_the_proxys_silhouette_and_the_pixel():
  dataset = ground_dataset()
  rays, rendered = rendered_ground(dataset, (20.5, 20.5))
  selection = place.support(dataset, 0, (20.5, 20.5), rays, rendered, size=0.6).selection(
      "primitive:box")
  figure = place.placement_figure(dataset, 0, selection, (20.5, 20.5))
  assert figure.shape == (SIZE, SIZE, 3)
  red = (figure[..., 0] > 0.7) & (figure[..., 1] < 0.45)
  assert 20 < red.sum() < SIZE * SIZE / 2
  np.testing.assert_array_equal(figure[20, 20], [1.0, 1.0, 0.0])  # The picked pixel.
  rows, _ = np.nonzero(red)
  assert rows.max() >= 18  # The box stands on the point: it reaches up from the pixel's row.


def test_views_are_named_by_index_or_image_name():
  names = ("images/a.png", "images/b.png", "other/b.png", "./train/0002")
  assert view_index("1", names) == 1 and view_index("a.png", names) == 0
  assert view_index("images/b.png", names) == 1
  assert view_index("0002.png", names) == view_index("train/0002", names) == 3
  with pytest.raises(InputError, match="more than one"):
    view_index("b.png", names)
  with pytest.raises(InputError, match="no training view"):
    view_index("c.png", names)



def test_a_box_from_two_rectangles_is_given_in_the_datasets_units():
  dataset = ground_dataset()
  eyes = np.array([[1.5, -1.2, 1.0], [-1.4, -1.3, 0.9]], np.float32)
  cameras = camera.Cameras.create(
      np.asarray(camera.look_at(eyes, np.array([0.1, 0.0, GROUND_Z], np.float32))),
      fx=SIZE * 1.1, width=SIZE, height=SIZE)
  dataset = Dataset(images=np.full((2, SIZE, SIZE, 3), 0.5, np.float32), cameras=cameras,
                    image_names=("a.png", "b.png"), scene_bounds=dataset.scene_bounds,
                    scene_kind="bounded", near=0.1, far=5.0, world_from_source=WORLD_FROM_SOURCE)
  cube = np.stack(np.meshgrid(*[[0.0, 0.2]] * 3, indexing="ij"), -1).reshape(-1, 3) + [
      0.0, 0.0, GROUND_Z]
  pixels = np.asarray(camera.project(cameras, cube)[0])
  rectangles = np.concatenate([pixels.min(1), pixels.max(1)], axis=1)
  selection = place.box_selection(dataset, [0, 1], rectangles)
  assert selection.kind == "box" and selection.frame == "source"
  # The cube in the source frame (scale 2 back, a quarter turn the other way) lies inside.
  source_cube = (np.linalg.inv(WORLD_FROM_SOURCE) @ np.c_[cube, np.ones(8)].T).T[:, :3]
  assert np.all(np.asarray(selection.box_min) <= source_cube.min(0) + 1e-5)
  assert np.all(np.asarray(selection.box_max) >= source_cube.max(0) - 1e-5)
  figure = place.placement_figure(dataset, 0, selection)
  assert ((figure[..., 0] > 0.7) & (figure[..., 1] < 0.45)).sum() > 20


def moved_handle(selection, dataset, turn_degrees=0.0, shift=(0.0, 0.0, 0.0)):
  """The selection after its handle is shifted (scene frame) and turned about the scene's z."""
  rotation, position = place.handle_pose(selection, dataset)
  angle = np.deg2rad(turn_degrees)
  turn = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0],
                   [0, 0, 1]])
  return place.moved_selection(selection, dataset, turn @ rotation,
                               position + np.asarray(shift))


PROXY = SelectionConfig(kind="proxy", proxy="primitive:cow", ground_position=(0.2, 0.1, 0.0),
                        up=(0.0, 0.0, 1.0), ground_size=0.6, heading_degrees=10.0)
BOX = SelectionConfig(kind="box", box_min=(-0.2, -0.1, 0.0), box_max=(0.3, 0.2, 0.4))


@pytest.mark.parametrize("selection", [PROXY, BOX], ids=["proxy", "box"])
def test_a_handle_left_where_it_is_leaves_the_selection_as_it_is(selection):
  assert moved_handle(selection, ground_dataset()) == selection


@pytest.mark.parametrize("selection", [PROXY, BOX], ids=["proxy", "box"])
def test_moving_the_handle_moves_the_selection_by_as_much_in_the_scene(selection):
  dataset = ground_dataset()
  moved = moved_handle(selection, dataset, shift=(0.05, -0.1, 0.02))
  before, after = (np.asarray(place.selection_mesh(chosen, dataset).vertices, np.float64)
                   for chosen in (selection, moved))
  np.testing.assert_allclose(after - before, np.broadcast_to([0.05, -0.1, 0.02], before.shape),
                             atol=1e-5)
  # In the dataset's units: the scene is the source at half scale, turned a quarter about z.
  if selection.kind == "proxy":
    np.testing.assert_allclose(np.subtract(moved.ground_position, selection.ground_position),
                               [-0.2, -0.1, 0.04], atol=1e-5)


def test_turning_a_proxys_handle_about_up_turns_its_heading():
  dataset = ground_dataset()
  turned = moved_handle(PROXY, dataset, turn_degrees=30.0)
  assert turned.heading_degrees == pytest.approx(40.0, abs=1e-3)
  np.testing.assert_allclose(turned.up, PROXY.up, atol=1e-6)
  assert turned.ground_position == PROXY.ground_position
  # The handle sits where the proxy now stands, turned as it is.
  rotation, position = place.handle_pose(turned, dataset)
  expected_rotation, _ = place.handle_pose(PROXY, dataset)
  angle = np.deg2rad(30.0)
  turn = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0],
                   [0, 0, 1]])
  np.testing.assert_allclose(rotation, turn @ expected_rotation, atol=1e-6)


def test_a_proxy_placed_by_a_similarity_has_no_handle():
  selection = SelectionConfig(kind="proxy", proxy="primitive:cow")
  with pytest.raises(InputError, match="no ground point") as error:
    place.handle_pose(selection, ground_dataset())
  assert error.value.field == "ground_position"


@pytest.mark.parametrize("flags, up, heading", [
    ((), [0.0, 0.0, 1.0], 0.0),  # The surface's normal.
    (("--up", "0", "1", "0", "--heading", "30"), [0.0, 1.0, 0.0], 30.0),
])
def test_signerf_place_stands_the_proxy_along_up_turned_by_heading(tmp_path, monkeypatch, capsys,
                                                                    flags, up, heading):
  dataset = ground_dataset()
  rays, rendered = rendered_ground(dataset, (21.5, 24.5))
  found = place.support(dataset, 0, (21.5, 24.5), rays, rendered, size=0.8)
  monkeypatch.setattr(place_command.evaluate, "load_run", lambda run: types.SimpleNamespace(
      model=None, variables=None, description={}))
  monkeypatch.setattr(place_command, "load_recorded_dataset", lambda description, split: dataset)
  monkeypatch.setattr(place_command.place, "locate", lambda *args, **kwargs: found)
  edit = tmp_path / "edit"
  assert cli.main(["place", "--run", str(tmp_path / "run"), "--edit", str(edit), "--view", "0",
                   "--pixel", "21.5", "24.5", "--proxy", "primitive:box", *flags]) == 0
  selection = json.loads(capsys.readouterr().out)["selection"]
  np.testing.assert_allclose(selection["up"], up, atol=1e-4)
  assert selection["heading_degrees"] == heading
  assert selection["mesh_up"] == [0.0, 1.0, 0.0]
  saved = (edit / "config.gin").read_text()
  assert "SelectionConfig.up = " in saved and "SelectionConfig.heading_degrees = " in saved
  assert (edit / "placement.png").is_file()
