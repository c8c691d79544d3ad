import numpy as np
import pytest
import trimesh

from signerf_jax.errors import InputError
from signerf_jax.geometry import mesh as mesh_lib
from signerf_jax.geometry import primitives


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".stl", ".glb", ".off"])
def test_formats_round_trip(tmp_path, suffix):
  original = primitives.capsule(0.2, 1.0, count=(6, 6))
  path = tmp_path / f"proxy{suffix}"
  original.to_trimesh().export(path)
  loaded = mesh_lib.load_mesh(path)
  np.testing.assert_allclose(loaded.bounds, original.bounds, atol=1e-5)
  assert loaded.faces.shape[1] == 3 and loaded.faces.dtype == np.int32
  assert loaded.source == str(path)


def test_polygon_faces_are_triangulated(tmp_path):
  path = tmp_path / "polygons.obj"
  path.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0.5 1.5 0\nv 2 0 0\nv 2 1 0\n"
                  "f 1 2 3 5 4\nf 2 6 7 3\n")
  loaded = mesh_lib.load_mesh(path)
  assert loaded.faces.shape == (5, 3)  # a pentagon (3) and a quad (2)
  area = 0.5 * np.linalg.norm(np.cross(loaded.triangles[:, 1] - loaded.triangles[:, 0],
                                       loaded.triangles[:, 2] - loaded.triangles[:, 0]), axis=-1)
  assert area.sum() == pytest.approx(1.25 + 1.0)


def test_scene_files_are_merged_into_one_mesh(tmp_path):
  scene = trimesh.Scene()
  scene.add_geometry(trimesh.creation.box((1, 1, 1)), node_name="body")
  scene.add_geometry(trimesh.creation.icosphere(1, 0.5), node_name="head",
                     transform=trimesh.transformations.translation_matrix((3.0, 0, 0)))
  path = tmp_path / "scene.glb"
  scene.export(path)
  loaded = mesh_lib.load_mesh(path)
  assert loaded.faces.shape[0] == 12 + 80
  np.testing.assert_allclose(loaded.bounds, [[-0.5, -0.5, -0.5], [3.5, 0.5, 0.5]], atol=1e-3)


def test_bad_files_are_input_errors_naming_the_file(tmp_path):
  with pytest.raises(InputError, match="mesh file not found") as error:
    mesh_lib.load_mesh(tmp_path / "missing.obj")
  assert error.value.path.endswith("missing.obj")
  text = tmp_path / "proxy.txt"
  text.write_text("hello")
  with pytest.raises(InputError, match="unsupported mesh format"):
    mesh_lib.load_mesh(text)
  cloud = tmp_path / "cloud.ply"
  trimesh.PointCloud(np.random.rand(10, 3)).export(cloud)
  with pytest.raises(InputError, match="PointCloud") as error:
    mesh_lib.load_mesh(cloud)
  assert error.value.path == str(cloud)
  empty = tmp_path / "empty.obj"
  empty.write_text("v 0 0 0\nv 1 0 0\n")
  with pytest.raises(InputError, match=str(empty)):
    mesh_lib.load_mesh(empty)
  broken = tmp_path / "broken.obj"
  broken.write_text("v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n")
  with pytest.raises(InputError, match="non-finite"):
    mesh_lib.load_mesh(broken)


def test_validate_rejects_degenerate_meshes():
  with pytest.raises(InputError, match="zero area"):
    mesh_lib.validate(mesh_lib.Mesh(np.zeros((3, 3), np.float32), np.array([[0, 1, 2]], np.int32),
                                    "flat"))
  with pytest.raises(InputError, match="out of range"):
    mesh_lib.validate(mesh_lib.Mesh(np.eye(3, dtype=np.float32), np.array([[0, 1, 3]], np.int32)))


def test_similarity_transform():
  matrix = mesh_lib.similarity_transform(2.0, (0.0, 0.0, 90.0), (1.0, 2.0, 3.0))
  np.testing.assert_allclose(matrix[:3, :3] @ [1.0, 0.0, 0.0] + matrix[:3, 3], [1.0, 4.0, 3.0],
                             atol=1e-12)
  box = mesh_lib.transform_mesh(primitives.box((1.0, 2.0, 3.0)), matrix)
  np.testing.assert_allclose(box.bounds, [[-1.0, 1.0, 0.0], [3.0, 3.0, 6.0]], atol=1e-5)
  with pytest.raises(InputError, match="rotation"):
    mesh_lib.similarity_transform(1.0, np.diag([1.0, 1.0, -1.0]))
  with pytest.raises(InputError, match="scale"):
    mesh_lib.similarity_transform(-1.0)


@pytest.mark.parametrize("up", [(0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (1.0, 1.0, 1.0)])
def test_place_on_ground(up):
  cow = primitives.primitive_cow()
  position = np.array([0.5, -1.0, 0.25])
  placed = mesh_lib.place_on_ground(cow, position, size=0.8, up=up, heading_degrees=30.0)
  up = np.asarray(up) / np.linalg.norm(up)
  heights = placed.vertices.astype(np.float64) @ up
  assert heights.min() == pytest.approx(position @ up, abs=1e-5)
  # The cow's own up (+y) now points along the scene's up: it stands taller than it is wide.
  assert np.ptp(heights) == pytest.approx(np.ptp(cow.vertices[:, 1]) * 0.8
                                          / np.max(np.ptp(cow.vertices, axis=0)), rel=1e-4)


def test_primitive_sizes():
  np.testing.assert_allclose(primitives.box((1.0, 2.0, 3.0)).bounds, [[-0.5, -1, -1.5],
                                                                      [0.5, 1, 1.5]])
  np.testing.assert_allclose(primitives.cylinder(0.5, 2.0).bounds[:, 1], [-1.0, 1.0], atol=1e-6)
  np.testing.assert_allclose(primitives.capsule(0.25, 2.0).bounds[:, 1], [-1.0, 1.0], atol=1e-6)
  with pytest.raises(InputError, match="diameter"):
    primitives.capsule(0.6, 1.0)
  with pytest.raises(InputError, match="radius"):
    primitives.sphere(0.0)


@pytest.mark.shared_data
def test_shared_spot_meshes_load_and_the_primitive_cow_matches_their_size(shared_data):
  control = mesh_lib.load_mesh(shared_data / "meshes/spot/spot_control_mesh.obj")
  assert control.faces.shape == (372, 3)  # quads and pentagons triangulated
  spot = mesh_lib.load_mesh(shared_data / "meshes/spot/spot_triangulated.obj")
  assert spot.faces.shape == (5856, 3)
  np.testing.assert_allclose(primitives.primitive_cow().bounds, spot.bounds, atol=0.15)


@pytest.mark.parametrize("up", [(0, 0, 1), (0, 1, 0), (0, -1, 0), (1, 2, -0.5)])
@pytest.mark.parametrize("heading", [0.0, 37.0, -120.0, 179.0])
def test_the_heading_of_an_upright_rotation_is_recovered(up, heading):
  rotation = mesh_lib.upright_rotation(up, (0.0, 1.0, 0.0), heading)
  np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
  found_up, found_heading = mesh_lib.heading_degrees_of(rotation, (0.0, 1.0, 0.0))
  np.testing.assert_allclose(found_up, np.asarray(up) / np.linalg.norm(up), atol=1e-9)
  assert found_heading == pytest.approx(heading, abs=1e-6)
  np.testing.assert_allclose(mesh_lib.upright_rotation(found_up, (0.0, 1.0, 0.0), found_heading),
                             rotation, atol=1e-9)


def test_any_rotation_is_an_upright_rotation_with_some_up_and_heading():
  rotation = trimesh.transformations.random_rotation_matrix(np.random.default_rng(0).random(3))
  up, heading = mesh_lib.heading_degrees_of(rotation[:3, :3], (0.0, 0.0, 1.0))
  np.testing.assert_allclose(mesh_lib.upright_rotation(up, (0.0, 0.0, 1.0), heading),
                             rotation[:3, :3], atol=1e-9)
