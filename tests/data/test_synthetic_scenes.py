import dataclasses

import gin
import numpy as np
import pytest
import trimesh

from signerf_jax import cli, configs, files, ownership
from signerf_jax.data import load_dataset, poses, synthetic, synthetic_render
from signerf_jax.errors import InputError

TINY_RIG = synthetic_render.CameraRig(image_size=32, num_views=8)


@pytest.fixture
def mesh_directory(tmp_path_factory):
  """A directory with one OBJ (a torus), so meshes are covered without the shared data."""
  directory = tmp_path_factory.mktemp("meshes")
  trimesh.creation.torus(major_radius=1.0, minor_radius=0.35, major_sections=20,
                         minor_sections=10).export(directory / "torus.obj")
  return directory


@pytest.fixture(autouse=True)
def clear_gin():
  yield
  gin.clear_config()


def pixel_rays_float64(cameras, index):
  """Pinhole rays through the pixel centres, [H*W, 3] each, computed independently."""
  rows, columns = np.mgrid[:cameras.height, :cameras.width] + 0.5
  local = np.stack([(columns - float(cameras.cx[index])) / float(cameras.fx[index]),
                    -(rows - float(cameras.cy[index])) / float(cameras.fy[index]),
                    -np.ones_like(rows)], -1).reshape(-1, 3)
  camera_to_world = np.asarray(cameras.camera_to_world[index], np.float64)
  directions = local @ camera_to_world[:, :3].T
  directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
  return np.broadcast_to(camera_to_world[:, 3], directions.shape), directions


def test_generation_is_deterministic_in_the_seed(tmp_path, mesh_directory):
  settings = synthetic.SceneSettings(mesh_directory=str(mesh_directory))
  for name, seed in (("first", 4), ("again", 4), ("other", 5)):
    synthetic_render.generate(tmp_path / name, seed, settings, TINY_RIG)
  written = sorted(p.relative_to(tmp_path / "first") for p in (tmp_path / "first").rglob("*.*")
                   if ownership.MARKER_FOLDER not in p.parts)  # The record of what it wrote.
  assert len(written) == 2 + 3 * 8  # transforms, scene + image, depth, ids per view
  for relative in written:
    assert (tmp_path / "first" / relative).read_bytes() == (
        tmp_path / "again" / relative).read_bytes(), relative
  assert (tmp_path / "first" / "scene.json").read_bytes() != (
      tmp_path / "other" / "scene.json").read_bytes()
  first = files.read_image(tmp_path / "first" / "images" / "frame_00000.png")
  other = files.read_image(tmp_path / "other" / "images" / "frame_00000.png")
  assert np.abs(first - other).max() > 0.2


def test_depth_matches_analytic_ray_plane_and_ray_sphere_depth():
  scene = synthetic.make_scene(0, synthetic.SceneSettings(num_primitives=1, num_meshes=0))
  center, radius = np.array([0.2, -0.1, 0.3]), 0.3
  sphere = dataclasses.replace(scene.objects[0], shape="sphere",
                               object_to_world=synthetic.affine(radius * np.eye(3), center))
  scene = dataclasses.replace(scene, objects=(sphere,))
  cameras = synthetic_render.make_cameras(TINY_RIG, scene.scene_bounds)
  _, depth, object_ids = synthetic_render.render(scene, cameras)
  half_size = scene.ground.object_to_world[0, 0]
  counts = np.zeros(3, int)
  for index in range(cameras.num_cameras):
    origins, directions = pixel_rays_float64(cameras, index)
    # Top of the ground: the plane z = 0 inside the square (cameras are above it).
    plane_t = -origins[:, 2] / directions[:, 2]
    plane_point = origins + plane_t[:, None] * directions
    on_top = (plane_t > 0) & np.all(np.abs(plane_point[:, :2]) < half_size - 0.02, -1)
    # Sphere: |o + t d - c| = r.
    offset = origins - center
    along = -np.sum(offset * directions, -1)
    squared = radius**2 - np.sum((offset + along[:, None] * directions)**2, -1)
    sphere_t = np.where(squared >= 0, along - np.sqrt(np.abs(squared)), np.inf)
    expected_t = np.minimum(np.where(on_top, plane_t, np.inf), sphere_t)
    known = np.isfinite(expected_t)
    forward = -np.asarray(cameras.camera_to_world[index, :, 2], np.float64)
    expected_depth = expected_t * (directions @ forward)
    np.testing.assert_allclose(depth[index].reshape(-1)[known], expected_depth[known],
                               atol=2e-5, rtol=1e-5)
    expected_ids = np.where(sphere_t < np.where(on_top, plane_t, np.inf), 1, 0)
    np.testing.assert_array_equal(object_ids[index].reshape(-1)[known], expected_ids[known])
    counts += [np.sum(known & (expected_ids == 0)), np.sum(expected_ids == 1), np.sum(~known)]
  assert np.all(counts > 100), counts  # ground, sphere and other pixels were all compared


def test_object_masks_agree_with_depth(mesh_directory):
  scene = synthetic.make_scene(2, synthetic.SceneSettings(mesh_directory=str(mesh_directory)))
  cameras = synthetic_render.make_cameras(TINY_RIG, scene.scene_bounds)
  rgb, depth, object_ids = synthetic_render.render(scene, cameras)
  missed = depth == 0
  assert np.all(object_ids[missed] == 0) and np.all(rgb[missed] == 1.0)
  assert set(np.unique(object_ids)) == {0, 1, 2, 3, 4}
  for removed in scene.objects:
    reduced = dataclasses.replace(scene, objects=tuple(
        shape for shape in scene.objects if shape is not removed))
    _, depth_without, _ = synthetic_render.render(reduced, cameras)
    # Removing an object changes depth exactly on its mask, and only to something farther.
    changed = depth_without != depth
    np.testing.assert_array_equal(changed, object_ids == removed.object_id)
    farther_or_missed = (depth_without > depth) | (depth_without == 0)
    assert np.all(farther_or_missed[changed])


def test_mask_edges_are_depth_discontinuities_seen_from_above():
  scene = synthetic.make_scene(1, synthetic.SceneSettings(num_meshes=0, num_primitives=4))
  rig = dataclasses.replace(TINY_RIG, image_size=48, num_views=3,
                            elevation_range_degrees=(80, 89))
  cameras = synthetic_render.make_cameras(rig, scene.scene_bounds)
  _, depth, object_ids = synthetic_render.render(scene, cameras)
  heights = []
  for index in range(cameras.num_cameras):
    origins, directions = pixel_rays_float64(cameras, index)
    cosines = directions @ -np.asarray(cameras.camera_to_world[index, :, 2], np.float64)
    points = origins + directions * (depth[index].reshape(-1) / cosines)[:, None]
    heights.append(points[:, 2].reshape(depth.shape[1:]))
  heights = np.stack(heights)
  edges = 0
  for axis in (1, 2):
    first = tuple(slice(None, -1) if dim == axis else slice(None) for dim in range(3))
    second = tuple(slice(1, None) if dim == axis else slice(None) for dim in range(3))
    boundary = ((object_ids[first] != object_ids[second])
                & (depth[first] > 0) & (depth[second] > 0))
    # Where an object stands on the ground, depth is continuous: exempt its lowest rim.
    object_height = np.minimum(np.where(object_ids[first] > 0, heights[first], np.inf),
                               np.where(object_ids[second] > 0, heights[second], np.inf))
    above_contact = boundary & (object_height > 0.05)
    jump = np.abs(depth[first] - depth[second])
    assert np.all(jump[above_contact] > 0.03)
    edges += above_contact.sum()
  assert edges > 50


def test_written_scene_loads_with_its_ground_truth(tmp_path, mesh_directory):
  settings = synthetic.SceneSettings(mesh_directory=str(mesh_directory))
  dataset, scene = synthetic_render.generate(tmp_path, 0, settings, TINY_RIG)
  loaded = load_dataset(tmp_path, split="all")
  assert loaded.scene_kind == "bounded" and loaded.num_images == 8
  np.testing.assert_array_equal(loaded.world_from_source, np.eye(4))
  np.testing.assert_array_equal(loaded.cameras.camera_to_world, dataset.cameras.camera_to_world)
  np.testing.assert_array_equal(loaded.depths, dataset.depths)
  np.testing.assert_array_equal(loaded.extras["object_masks"], dataset.extras["object_masks"])
  np.testing.assert_allclose(loaded.images, dataset.images, atol=0.5 / 255 + 1e-6)
  lower, upper = loaded.scene_bounds
  assert np.all(lower >= -1) and np.all(upper <= 1)
  assert loaded.near == pytest.approx(dataset.near) and loaded.far == pytest.approx(dataset.far)

  description = files.read_json(tmp_path / "scene.json")
  assert description["generator"]["cameras"]["num_views"] == 8
  objects = description["objects"]
  assert [entry["object_id"] for entry in objects] == [1, 2, 3, 4]
  assert {entry["shape"] for entry in objects} >= {"mesh"}
  spot = description["free_spot"]
  for entry in objects:
    assert np.min(entry["bounds"], 0)[2] == pytest.approx(0.0, abs=1e-6)  # on the ground
    gap = np.linalg.norm(np.subtract(entry["footprint"]["center"], spot["center"][:2]))
    assert gap > entry["footprint"]["radius"] + spot["radius"]
  # A mesh's transform maps the OBJ file's own vertices into the scene, onto the ground.
  mesh_entry = next(entry for entry in objects if entry["shape"] == "mesh")
  vertices = trimesh.load(mesh_entry["mesh_path"], force="mesh").vertices
  placed = poses.transform_points(np.asarray(mesh_entry["transform"]), vertices)
  np.testing.assert_allclose([placed.min(0), placed.max(0)], mesh_entry["bounds"], atol=1e-9)


@pytest.mark.parametrize("layout", synthetic_render.CAMERA_LAYOUTS)
def test_camera_layouts_look_at_the_scene_centre(layout):
  bounds = np.array([[-1.0, -1.0, -0.2], [1.0, 1.0, 0.6]])
  rig = synthetic_render.CameraRig(layout=layout, num_views=20, distance=3.0)
  cameras = synthetic_render.make_cameras(rig, bounds)
  target = bounds.mean(0)
  offsets = np.asarray(cameras.positions, np.float64) - target
  np.testing.assert_allclose(np.linalg.norm(offsets, axis=-1), 3.0, rtol=1e-5)
  np.testing.assert_allclose(np.asarray(cameras.forward), -offsets / 3.0, atol=1e-5)
  elevation = np.degrees(np.arcsin(offsets[:, 2] / 3.0))
  if layout == "sphere":
    assert elevation.min() < -60 and elevation.max() > 60
  elif layout == "hemisphere":
    assert 15 <= elevation.min() and elevation.max() <= 70
  else:
    np.testing.assert_allclose(elevation, 42.5, atol=1e-3)
    assert np.all(offsets[:, 1] < 0)  # in front of the scene, facing +y
    azimuth = np.degrees(np.arctan2(offsets[:, 0], -offsets[:, 1]))
    assert azimuth.max() - azimuth.min() == pytest.approx(120 * 19 / 20, abs=1e-3)


@pytest.mark.parametrize("make, field", [
    (lambda: synthetic.SceneSettings(ground_half_size=1.0), "SceneSettings.ground_half_size"),
    (lambda: synthetic.SceneSettings(object_radius_range=(0.3, 0.2)),
     "SceneSettings.object_radius_range"),
    (lambda: synthetic_render.CameraRig(layout="spiral"), "CameraRig.layout"),
    (lambda: synthetic_render.CameraRig(num_views=0), "CameraRig.num_views"),
])
def test_bad_generator_settings_are_refused_when_built(make, field):
  with pytest.raises(InputError) as error:
    make()
  assert error.value.field == field


def test_a_scene_too_crowded_to_place_names_its_settings(tmp_path):
  settings = synthetic.SceneSettings(num_primitives=40, num_meshes=0)
  with pytest.raises(InputError) as error:
    synthetic_render.generate(tmp_path, 0, settings, TINY_RIG)
  assert error.value.field.startswith("synthetic_scene")


def test_synthesize_command_writes_the_scene_and_its_config(tmp_path, capsys):
  code = cli.main(["synthesize", "--out", str(tmp_path / "scene"), "--seed", "3",
                   "--gin_param", "synthetic_cameras.image_size = 24",
                   "--gin_param", "synthetic_cameras.num_views = 5",
                   "--gin_param", "synthetic_scene.num_meshes = 0"])
  assert code == 0
  summary = capsys.readouterr().out.strip()
  assert summary.startswith("signerf synthesize: 5 views of 24x24 px, 3 objects (seed 3)")
  assert str(tmp_path / "scene") in summary and summary.endswith(" s")
  assert "synthetic_cameras.num_views = 5" in (tmp_path / "scene" / "config.gin").read_text()
  assert load_dataset(tmp_path / "scene", split="all").num_images == 5


def test_gin_files_bind_the_generator():
  configs.parse_gin(["synthetic_large"])
  rig = configs.build(synthetic_render.CameraRig)
  assert rig.image_size == 256 and rig.num_views == 100
  assert configs.build(synthetic.SceneSettings).num_meshes == 3
