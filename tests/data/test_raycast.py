import numpy as np
import pytest
import trimesh

from signerf_jax.data import raycast


def random_rays(count, seed=0):
  """Rays from a shell of radius 3 aimed near the origin (some miss), unit directions."""
  rng = np.random.default_rng(seed)
  origins = rng.normal(size=(count, 3))
  origins *= 3 / np.linalg.norm(origins, axis=-1, keepdims=True)
  directions = rng.uniform(-1.3, 1.3, (count, 3)) - origins
  return origins, directions / np.linalg.norm(directions, axis=-1, keepdims=True)


def reference_hits(mesh, origins, directions):
  """First-hit distances from trimesh's own ray caster (inf where rays miss)."""
  intersector = trimesh.ray.ray_triangle.RayMeshIntersector(mesh)
  locations, ray_index, _ = intersector.intersects_location(origins, directions,
                                                            multiple_hits=False)
  t = np.full(len(origins), np.inf)
  t[ray_index] = np.linalg.norm(locations - origins[ray_index], axis=-1)
  return t


@pytest.mark.parametrize("name, intersect, mesh, tolerance", [
    ("box", raycast.intersect_box, trimesh.creation.box(extents=(2, 2, 2)), 1e-9),
    ("cylinder", raycast.intersect_cylinder,
     trimesh.creation.cylinder(radius=1.0, height=2.0, sections=512), 2e-4),
])
def test_primitives_match_their_triangulated_shapes(name, intersect, mesh, tolerance):
  origins, directions = random_rays(400, seed=len(name))
  t, normals = intersect(origins, directions)
  expected = reference_hits(mesh, origins, directions)
  assert 100 < np.sum(np.isfinite(t)) < 400
  np.testing.assert_array_equal(np.isfinite(t), np.isfinite(expected))
  hit = np.isfinite(t)
  np.testing.assert_allclose(t[hit], expected[hit], atol=tolerance)
  # Normals point out of the shape at the hit, against the incoming ray.
  assert np.all(np.sum(normals[hit] * directions[hit], -1) < 0)
  assert np.all(normals[~hit] == 0)


def test_sphere_matches_the_geometric_solution():
  origins, directions = random_rays(400, seed=5)
  t, normals = raycast.intersect_sphere(origins, directions)
  # Closest approach of the ray to the centre, then back along the chord.
  along = -np.sum(origins * directions, -1)
  squared_miss = np.sum((origins + along[:, None] * directions)**2, -1)
  expected = np.where(squared_miss <= 1, along - np.sqrt(np.maximum(1 - squared_miss, 0)), np.inf)
  assert 100 < np.sum(np.isfinite(expected)) < 400
  np.testing.assert_allclose(t, expected, atol=1e-12)
  hit = np.isfinite(t)
  np.testing.assert_allclose(normals[hit], origins[hit] + t[hit, None] * directions[hit])


def test_distances_survive_a_scaled_frame():
  """Rays mapped by an inverse transform keep the world distance as their parameter."""
  origins, directions = random_rays(300, seed=7)
  scale = np.array([0.5, 2.0, 1.5])
  t, _ = raycast.intersect_sphere(origins / scale, directions / scale)
  hit = np.isfinite(t)
  assert hit.sum() > 100
  points = origins[hit] + t[hit, None] * directions[hit]
  np.testing.assert_allclose(np.linalg.norm(points / scale, axis=-1), 1.0, atol=1e-9)
  # It is the first hit: the segment before it stays outside the ellipsoid.
  fractions = np.linspace(0, 0.999, 50)[:, None, None]
  before = origins[hit] + fractions * t[hit, None] * directions[hit]
  assert np.all(np.linalg.norm(before / scale, axis=-1) > 1)


@pytest.mark.parametrize("cluster_size", [1, 5, 32])
def test_clustered_mesh_matches_trimesh_on_a_torus(cluster_size):
  torus = trimesh.creation.torus(major_radius=0.8, minor_radius=0.3, major_sections=24,
                                 minor_sections=12)
  clusters = raycast.TriangleClusters.build(torus.vertices, torus.faces, torus.vertex_normals,
                                            cluster_size)
  assert clusters.corners.shape[1] == cluster_size
  origins, directions = random_rays(600, seed=3)
  t, normals = raycast.intersect_mesh(clusters, origins, directions, rays_per_chunk=128)
  expected = reference_hits(torus, origins, directions)
  assert np.sum(np.isfinite(expected)) > 150
  np.testing.assert_array_equal(np.isfinite(t), np.isfinite(expected))
  hit = np.isfinite(t)
  np.testing.assert_allclose(t[hit], expected[hit], atol=1e-9)
  # Interpolated vertex normals stay close to the true torus normal at the hit.
  points = origins[hit] + t[hit, None] * directions[hit]
  ring = points * [1, 1, 0]
  ring *= 0.8 / np.linalg.norm(ring, axis=-1, keepdims=True)
  true_normals = (points - ring) / np.linalg.norm(points - ring, axis=-1, keepdims=True)
  unit = normals[hit] / np.linalg.norm(normals[hit], axis=-1, keepdims=True)
  assert np.min(np.sum(unit * true_normals, -1)) > 0.95


def test_rays_parallel_to_box_faces():
  origins = np.array([[0.5, 0.5, 3.0], [1.0, 0.0, 3.0], [2.0, 0.0, 3.0], [0.0, 0.0, 3.0]])
  directions = np.array([[0, 0, -1.0], [0, 0, -1.0], [0, 0, -1.0], [0, 0, 1.0]])
  t, normals = raycast.intersect_box(origins, directions)
  np.testing.assert_array_equal(t, [2.0, 2.0, np.inf, np.inf])
  np.testing.assert_array_equal(normals[0], [0, 0, 1])
