import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from signerf_jax.nerf import sampling

BOX = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], np.float32)
# (origin, direction, expected (near, far) or None for a miss)
RAYS = [
    ((0.0, 0.0, 3.0), (0.0, 0.0, -1.0), (2.0, 4.0)),  # axis-parallel, hits
    ((1.0, 0.0, 3.0), (0.0, 0.0, -1.0), None),  # axis-parallel in a face plane: grazes, no interior
    ((0.0, 1.0 - 1e-6, 3.0), (0.0, 0.0, -1.0), (2.0, 4.0)),  # axis-parallel, just inside a face
    ((2.0, 0.0, 3.0), (0.0, 0.0, -1.0), None),  # axis-parallel, misses
    ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0)),  # starts inside
    ((0.0, 0.0, 3.0), (0.0, 0.0, 1.0), None),  # box behind the origin
    ((3.0, 3.0, 0.0), (-0.7071068, 0.7071068, 0.0), None),  # passes beside
    ((-3.0, -3.0, -3.0), (0.5773503, 0.5773503, 0.5773503), (3.4641016, 6.9282032)),  # diagonal
]


@pytest.mark.parametrize("origin, direction, expected", RAYS)
def test_intersect_aabb_is_finite_and_exact(origin, direction, expected):
  origin, direction = jnp.asarray(origin), jnp.asarray(direction)
  t_near, t_far, hit = sampling.intersect_aabb(origin, direction, BOX)
  gradient = jax.grad(lambda o: sum(sampling.intersect_aabb(o, direction, BOX)[:2]))(origin)
  assert np.isfinite(t_near) and np.isfinite(t_far) and np.all(np.isfinite(gradient))
  assert 0 <= float(t_near) <= float(t_far)
  if expected is None:
    assert not bool(hit) and float(t_near) == float(t_far)
  else:
    assert bool(hit)
    np.testing.assert_allclose([t_near, t_far], expected, rtol=1e-5, atol=1e-5)


DIRECTIONS = [np.array(d, np.float32) for d in itertools.product((-1.0, 0.0, 1.0), repeat=3)
              if any(d)]


@pytest.mark.parametrize("direction", DIRECTIONS, ids=lambda d: str(d.tolist()))
@pytest.mark.parametrize("origin", [(0.1, 0.2, -0.3), (3.0, 0.2, -0.3), (3.0, 3.0, 3.0),
                                    (1.0, 0.0, 0.0), (1.0, 1.0, 0.0)])
def test_the_closed_box_interval_with_axis_parallel_rays(origin, direction):
  # Box [-1, 1]^3; compare with dense sampling along the ray. Origins on the boundary (touching
  # a face, an edge) make the "parallel to a slab, exactly on its boundary" case.
  origin = np.asarray(origin, np.float32)
  direction = direction / np.linalg.norm(direction)
  entry, exit_, hits = sampling.ray_box_interval(origin, direction, -np.ones(3), np.ones(3))
  samples = np.linspace(0, 10, 100001)
  points = origin + samples[:, None] * direction
  inside = np.all(np.abs(points) <= 1 + 1e-6, -1)
  assert bool(hits) == inside.any()
  assert not np.isnan(entry) and not np.isnan(exit_)
  if inside.any():
    assert float(entry) == pytest.approx(samples[inside].min(), abs=2e-4)
    assert float(exit_) == pytest.approx(samples[inside].max(), abs=2e-4)


@pytest.mark.parametrize("closed", [True, False], ids=["closed", "open"])
def test_a_grazing_ray_touches_only_the_closed_box(closed):
  """Selections count a ray along a face as meeting the box; volume sampling does not (no
  interior to sample). Both are the same slab test."""
  direction = np.array([1.0, 0.0, 0.0])
  along_face = sampling.ray_box_interval(np.array([-5.0, 1.0, 0.0]), direction, -np.ones(3),
                                         np.ones(3), closed)
  touching_an_edge = sampling.ray_box_interval(np.array([-5.0, -3.0, 0.0]),
                                               np.array([1.0, 1.0, 0.0]), -np.ones(3),
                                               np.ones(3), closed)
  assert bool(along_face[2]) == bool(touching_an_edge[2]) == closed
  if closed:
    assert float(along_face[0]) == 4.0 and float(along_face[1]) == 6.0
  _, _, misses = sampling.ray_box_interval(np.array([-5.0, 1.0 + 1e-6, 0.0]), direction,
                                           -np.ones(3), np.ones(3), closed)
  assert not bool(misses)


def test_stratified_and_marching_edges_stay_sorted_inside_the_range():
  key = jax.random.PRNGKey(0)
  near, far = jnp.array([1.0, 2.0, 3.0]), jnp.array([2.0, 2.0, 7.0])
  for randomized in (False, True):
    edges = sampling.stratified_edges(key, near, far, 16, randomized)
    assert edges.shape == (3, 17)
    assert np.all(np.diff(edges, axis=-1) >= 0)
    assert np.all(edges >= near[:, None] - 1e-6) and np.all(edges <= far[:, None] + 1e-6)
    marched = sampling.marching_edges(key, near, far, 0.1, 64, randomized)
    assert np.all(np.diff(marched, axis=-1) >= 0) and np.all(marched <= far[:, None])
    # Steps are exactly 0.1 wherever they do not hit the far bound.
    inner = np.diff(np.asarray(marched[2]))
    np.testing.assert_allclose(inner[1:40], 0.1, atol=1e-5)


def test_spacing_round_trips_and_infinity_stays_finite():
  t = jnp.array([0.0, 0.3, 1.0, 2.0, 50.0])
  np.testing.assert_allclose(sampling.spacing_to_distance(sampling.distance_to_spacing(t, 1.0),
                                                          1.0), t, rtol=1e-4)
  assert float(sampling.spacing_to_distance(jnp.float32(2.0), 1.0)) == sampling.MAX_DISTANCE
  edges = sampling.spaced_edges(jax.random.PRNGKey(0), jnp.array([0.1]), jnp.array([jnp.inf]),
                                32, True, 1.0)
  assert np.all(np.isfinite(edges)) and np.all(np.diff(edges) >= 0)


def test_pdf_sampling_follows_the_weights():
  edges = jnp.linspace(0.0, 10.0, 11)[None]
  weights = jnp.zeros((1, 10)).at[0, 7].set(1.0)
  samples = sampling.sample_pdf(jax.random.PRNGKey(0), edges, weights, 64, True, padding=0.0)
  centres = np.asarray(sampling.midpoints(samples))
  assert np.all(np.diff(samples) >= 0)
  assert np.mean((centres >= 7) & (centres <= 8)) > 0.95
  # All-zero weights (an empty ray) still give valid, spread-out edges.
  uniform = sampling.sample_pdf(jax.random.PRNGKey(1), edges, jnp.zeros((1, 10)), 10, False)
  np.testing.assert_allclose(uniform, edges, atol=1e-4)


def test_contraction_keeps_the_inner_box_and_bounds_everything():
  points = jnp.array([[0.5, -0.2, 0.9], [3.0, 0.0, 0.0], [1e10, -1e10, 5.0], [0.0, 0.0, 0.0]])
  contracted = sampling.contract(points)
  np.testing.assert_allclose(contracted[0], points[0])
  np.testing.assert_allclose(contracted[1], [2 - 1 / 3, 0, 0], rtol=1e-6)
  assert np.all(np.abs(contracted) <= 2.0) and np.all(np.isfinite(contracted))
  gradient = jax.grad(lambda p: jnp.sum(sampling.contract(p)))(points)
  assert np.all(np.isfinite(gradient))


@pytest.mark.parametrize("direction", [[1.0, 0.3, -0.2], [0.2, -1.0, 0.9], [1.0, 1.0, 1.0]])
def test_contraction_is_continuous_with_a_finite_jacobian_and_identity_inside(direction):
  direction = np.asarray(direction) / np.max(np.abs(direction))  # L-inf norm 1: the border
  jacobian = jax.jacfwd(sampling.contract)
  for scale in (0.3, 0.999):
    np.testing.assert_allclose(jacobian(jnp.asarray(scale * direction, jnp.float32)), np.eye(3),
                               atol=1e-6)
  inside, outside = (jnp.asarray(scale * direction, jnp.float32) for scale in (1 - 1e-4, 1 + 1e-4))
  np.testing.assert_allclose(sampling.contract(inside), sampling.contract(outside), atol=1e-3)
  # The Jacobian does not jump across the border (within the step's own change).
  np.testing.assert_allclose(jacobian(inside), jacobian(outside), atol=2e-3)
  for scale in (2.0, 1e3, 1e9):
    assert np.all(np.isfinite(jacobian(jnp.asarray(scale * direction, jnp.float32))))


def test_perspective_divides_by_depth_along_minus_z():
  offsets = jnp.array([[1.0, 2.0, -4.0], [0.0, 0.0, -0.5], [3.0, -1.0, 2.0]])
  warped = np.asarray(sampling.perspective(offsets))
  np.testing.assert_allclose(warped[:2], [[0.25, 0.5, 0.25], [0.0, 0.0, 2.0]], rtol=1e-6)
  assert np.all(np.isfinite(warped[2]))  # behind the camera: finite, far outside any grid


@pytest.mark.parametrize("offset", [(0.3, -0.2, -0.5), (1e-3, 0.0, -1e-3), (5.0, 5.0, -1e4),
                                    (0.0, 0.0, 0.0), (1.0, 1.0, 2.0)])
def test_perspective_has_finite_gradients(offset):
  jacobian = jax.jacfwd(sampling.perspective)(jnp.asarray(offset, jnp.float32))
  assert np.all(np.isfinite(jacobian))


def test_uncontract_and_unperspective_invert_their_warps():
  points = np.array([[0.3, -0.9, 0.2], [3.0, 0.5, -1.0], [-40.0, 2.0, 7.0], [0.0, 0.0, -1e3]],
                    np.float32)
  np.testing.assert_allclose(sampling.uncontract(sampling.contract(points)), points, rtol=1e-4)
  in_front = points - np.array([0.0, 0.0, 50.0], np.float32)  # Every point ahead of the camera.
  np.testing.assert_allclose(sampling.unperspective(sampling.perspective(in_front)), in_front,
                             rtol=1e-5)
  assert np.all(np.isfinite(sampling.uncontract(np.array([[2.0, 0.0, 0.0]], np.float32))))
