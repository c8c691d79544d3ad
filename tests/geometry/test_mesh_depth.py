import jax
import numpy as np
import pytest
from trimesh.ray.ray_triangle import RayMeshIntersector

from signerf_jax import camera
from signerf_jax.geometry import mesh as mesh_lib
from signerf_jax.geometry import mesh_depth
from signerf_jax.geometry import primitives

SHARED_MESHES = ["spot/spot_triangulated.obj", "spot/spot_control_mesh.obj", "bunny_lowpoly.obj",
                 "teddy.obj", "teapot.obj"]


def orbit_cameras(target, distance, size=48, distortion=None, count=3, up=(0.0, 0.0, 1.0),
                  fisheye=False):
  angles = np.linspace(0.3, 2 * np.pi + 0.3, count, endpoint=False)
  eyes = np.stack([np.cos(angles), np.sin(angles), 0.5 + 0.3 * np.cos(3 * angles)], -1)
  eyes = np.asarray(target) + distance * eyes / np.linalg.norm(eyes, axis=-1, keepdims=True)
  camera_to_world = camera.look_at(eyes.astype(np.float32), np.asarray(target, np.float32), up)
  return camera.Cameras.create(camera_to_world, fx=size * 1.1, fy=size * 1.05, cx=size / 2 + 0.7,
                               cy=size / 2 - 0.4, width=size, height=size, distortion=distortion,
                               fisheye=fisheye)


def trimesh_distance(mesh: mesh_lib.Mesh, cameras: camera.Cameras) -> np.ndarray:
  """Ray distance of the nearest hit along every pixel ray, float64 trimesh, +inf on a miss."""
  intersector = RayMeshIntersector(mesh.to_trimesh())
  result = []
  for index in range(cameras.num_cameras):
    rays = camera.image_rays(cameras, index)
    origins = np.asarray(rays.origins, np.float64).reshape(-1, 3)
    directions = np.asarray(rays.directions, np.float64).reshape(-1, 3)
    locations, ray_index, _ = intersector.intersects_location(origins, directions,
                                                              multiple_hits=False)
    distance = np.full(len(origins), np.inf)
    distance[ray_index] = np.linalg.norm(locations - origins[ray_index], axis=-1)
    result.append(distance.reshape(cameras.height, cameras.width))
  return np.stack(result)


def render(mesh, cameras, tile_size=4, padded_triangles=1024, capacity=16384):
  """`mesh_depth` with the mesh padded to a fixed size, so the tests share compilations."""
  triangles = np.asarray(mesh.triangles)
  padding = np.repeat(triangles[:1], padded_triangles - len(triangles), axis=0)
  result = mesh_depth.mesh_depth(np.concatenate([triangles, padding]), cameras, tile_size,
                                 capacity, np.int32(len(triangles)))
  assert not np.asarray(result.overflow).any()
  return result


def assert_matches_trimesh(mesh, cameras, **render_options):
  result = render(mesh, cameras, **render_options)
  expected = trimesh_distance(mesh, cameras)
  distance = np.asarray(result.distance)
  np.testing.assert_array_equal(np.isfinite(distance), np.isfinite(expected))
  assert np.isfinite(expected).any()
  hit = np.isfinite(expected)
  np.testing.assert_allclose(distance[hit], expected[hit], rtol=1e-4)
  # z-depth is the ray distance projected on the optical axis.
  cosine = np.stack([camera.image_rays(cameras, i).cos_to_optical_axis
                     for i in range(cameras.num_cameras)])
  np.testing.assert_allclose(np.asarray(result.z_depth)[hit], (expected * cosine)[hit], rtol=1e-4)
  # The reported triangle is really hit at the reported distance.
  index = np.asarray(result.triangle_index)
  assert np.all((index >= 0) == hit)
  return result


@pytest.mark.slow
@pytest.mark.parametrize("proxy", [
    primitives.box((1.0, 0.6, 0.8)),
    primitives.sphere(0.5, subdivisions=2),
    primitives.cylinder(0.3, 1.0, sections=12),
    primitives.capsule(0.25, 1.0, count=(8, 8)),
    primitives.primitive_cow(),
], ids=lambda proxy: proxy.source)
@pytest.mark.parametrize("distortion, fisheye", [
    (None, False), ((-0.2, 0.05, 0.002, -0.001), False),
    ((0.3, -0.1, 0.002, -0.001, 0.01, 0.5, -0.02, 0.004), False),
    ((0.05, -0.01, 0.002, -0.0005), True)], ids=["pinhole", "distorted", "rational", "fisheye"])
def test_primitives_match_trimesh_ray_casting(proxy, distortion, fisheye):
  cameras = orbit_cameras(np.zeros(3), 2.5, distortion=distortion, fisheye=fisheye)
  assert_matches_trimesh(proxy, cameras)


@pytest.mark.slow
@pytest.mark.parametrize("distortion", [None, (-0.2, 0.05, 0.002, -0.001)],
                         ids=["pinhole", "distorted"])
def test_the_sizing_wrapper_undistorts_exactly_where_the_cameras_need_it(distortion):
  """render_mesh_depth leaves the undistortion out of the program for ideal pinholes (the
  reference views), with the same depths, and keeps it for distorted cameras."""
  proxy = primitives.primitive_cow()
  cameras = orbit_cameras(np.zeros(3), 2.5, distortion=distortion)
  result = mesh_depth.render_mesh_depth(proxy, cameras)
  expected = trimesh_distance(proxy, cameras)
  np.testing.assert_array_equal(np.asarray(result.hit), np.isfinite(expected))
  hit = np.isfinite(expected)
  np.testing.assert_allclose(np.asarray(result.distance)[hit], expected[hit], rtol=1e-4)
  if distortion is None:
    with_undistortion = mesh_depth.mesh_depth(proxy.triangles, cameras, capacity=16384,
                                              undistort=True)
    np.testing.assert_array_equal(np.asarray(result.z_depth),
                                  np.asarray(with_undistortion.z_depth))


@pytest.mark.slow
def test_fisheye_rays_past_90_degrees_hit_nothing_and_the_others_match_trimesh():
  """A 250-degree fisheye inside a box: the walls in front are exact, the rays behind the
  camera plane (no positive z-depth) are misses."""
  proxy = primitives.box((2.0, 3.0, 2.5))
  eye = np.array([[0.2, -0.3, 0.1]], np.float32)
  camera_to_world = camera.look_at(eye, np.array([1.0, 0.5, 0.3], np.float32))
  cameras = camera.Cameras.create(camera_to_world, fx=np.hypot(24, 24) / np.deg2rad(125.0),
                                  width=48, height=48, fisheye=True)
  result = render(proxy, cameras)
  cosine = np.asarray(camera.image_rays(cameras, 0).cos_to_optical_axis)
  assert np.any(cosine < -0.5)
  assert not np.asarray(result.hit)[0][cosine <= 0].any()
  in_front = cosine > 1e-3  # well clear of the clamp at lens.MAX_PLANE_ANGLE
  expected = trimesh_distance(proxy, cameras)[0]
  np.testing.assert_array_equal(np.asarray(result.hit)[0][in_front], True)
  np.testing.assert_allclose(np.asarray(result.distance)[0][in_front], expected[in_front],
                             rtol=1e-4)


@pytest.mark.slow
@pytest.mark.parametrize("tile_size", [3, 8])
def test_tile_size_and_odd_image_sizes_do_not_change_the_result(tile_size):
  proxy = primitives.sphere(0.5, subdivisions=1)
  eye = np.array([[2.0, 0.3, 0.4]], np.float32)
  cameras = camera.Cameras.create(camera.look_at(eye, np.zeros(3, np.float32)), fx=40.0,
                                  width=37, height=29)
  reference = render(proxy, cameras, tile_size=4)
  result = render(proxy, cameras, tile_size=tile_size)
  np.testing.assert_array_equal(result.triangle_index, reference.triangle_index)
  np.testing.assert_allclose(result.z_depth, reference.z_depth, rtol=1e-6)


@pytest.mark.slow
def test_camera_inside_a_box_sees_the_walls_around_it():
  # Most triangles straddle the camera plane: their projection is unbounded.
  proxy = primitives.box((2.0, 3.0, 2.5))
  eyes = np.array([[0.2, -0.3, 0.1], [0.0, 0.0, 0.0], [0.5, 0.9, -0.7]], np.float32)
  targets = np.array([[1.0, 0.5, 0.3], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]], np.float32)
  cameras = camera.Cameras.create(camera.look_at(eyes, targets), fx=20.0, width=48, height=48)
  result = assert_matches_trimesh(proxy, cameras)
  assert np.asarray(result.hit).all()


def test_analytic_sphere_depth():
  # An inscribed icosphere: its depth is never nearer than the sphere's and at most the
  # polyhedron's sagitta farther.
  radius, center = 0.7, np.array([0.1, -0.2, 0.3])
  proxy = mesh_lib.transform_mesh(primitives.sphere(radius, subdivisions=4),
                                  mesh_lib.similarity_transform(1.0, None, center))
  cameras = orbit_cameras(center, 3.0, size=64)
  result = render(proxy, cameras, padded_triangles=len(proxy.faces))
  for index in range(cameras.num_cameras):
    rays = camera.image_rays(cameras, index)
    origins = np.asarray(rays.origins, np.float64)
    directions = np.asarray(rays.directions, np.float64)
    offset = origins - center
    along = np.sum(offset * directions, -1)
    discriminant = along**2 - (np.sum(offset**2, -1) - radius**2)
    analytic = np.where(discriminant >= 0, -along - np.sqrt(np.maximum(discriminant, 0)), np.inf)
    distance = np.asarray(result.distance[index], np.float64)
    interior = discriminant > 0.05 * radius**2  # away from the silhouette
    assert np.isfinite(distance[interior]).all()
    assert np.all(distance[interior] >= analytic[interior] - 1e-5)
    # Subdivision 4: the faces sit at most ~1.2e-3 * radius inside the sphere; the ray's slant
    # at the edge of `interior` stretches that by up to ~4.5x.
    np.testing.assert_allclose(distance[interior], analytic[interior], atol=6e-3 * radius)
    assert not np.isfinite(distance[discriminant < 0]).any()


@pytest.mark.slow
def test_overflow_is_reported_and_avoided():
  proxy = primitives.sphere(0.5, subdivisions=2)
  cameras = orbit_cameras(np.zeros(3), 2.0)
  needed = np.asarray(mesh_depth.count_pairs(proxy.triangles, cameras))
  small = mesh_depth.mesh_depth(proxy.triangles, cameras, capacity=int(needed.min()) // 2)
  assert np.asarray(small.overflow).all()
  assert not np.asarray(mesh_depth.render_mesh_depth(proxy, cameras).overflow).any()


@pytest.mark.slow
def test_no_recompilation_for_new_cameras_of_the_same_shape():
  proxy = primitives.box((1.0, 1.0, 1.0))
  first = orbit_cameras(np.zeros(3), 3.0)
  second = orbit_cameras(np.array([0.1, 0.0, 0.0]), 3.5)
  mesh_depth.mesh_depth(proxy.triangles, first, capacity=4096).z_depth.block_until_ready()
  size = mesh_depth.mesh_depth._cache_size()
  mesh_depth.mesh_depth(proxy.triangles, second, capacity=4096).z_depth.block_until_ready()
  assert mesh_depth.mesh_depth._cache_size() == size


@pytest.mark.slow
@pytest.mark.shared_data
@pytest.mark.parametrize("name", SHARED_MESHES)
def test_shared_meshes_match_trimesh_ray_casting(shared_data, name):
  proxy = mesh_lib.load_mesh(shared_data / "meshes" / name)
  lower, upper = proxy.bounds
  center = (lower + upper) / 2
  cameras = orbit_cameras(center, 1.8 * float(np.linalg.norm(upper - lower)), size=64,
                          up=(0.0, 1.0, 0.0))
  assert_matches_trimesh(proxy, cameras, padded_triangles=8192, capacity=32768)


def test_jit_compatible_inside_a_larger_function():
  proxy = primitives.box((1.0, 1.0, 1.0))
  cameras = orbit_cameras(np.zeros(3), 3.0, size=16)

  @jax.jit
  def covered_fraction(triangles, cameras):
    return mesh_depth.mesh_depth(triangles, cameras, capacity=2048).hit.mean()

  assert 0 < float(covered_fraction(proxy.triangles, cameras)) < 1
