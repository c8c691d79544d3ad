"""The visual hull of RGBA photos (`nerf.visual_hull`) and carved occupancy cells: ten cameras
photograph a sphere; every cell the sphere touches stays, the photos' empty space is carved;
cells no photo sees are carved, cells a photo sees only in part are judged by the others; carved
cells are never refreshed nor occupied; training on photos with alpha carves."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from analytic_scene import SPHERE_RADIUS
from small_nerf import SMALL_CONFIG, small_model

from signerf_jax import camera
from signerf_jax.nerf import capture_choices, occupancy, training_run, visual_hull

SIZE = 48
RESOLUTION = 24
BALL_RADIUS = 0.3


def from_unit_cube(points):
  """The scene box [-1, 1]^3."""
  return np.asarray(points) * 2.0 - 1.0


def cell_centres():
  unit = (np.stack(np.meshgrid(*[np.arange(RESOLUTION)] * 3, indexing="ij"), -1) + 0.5)
  return from_unit_cube(unit / RESOLUTION)


def ring_cameras(centre=(0.0, 0.0, 0.0), focal=50.0):
  """Eight cameras on a circle of radius 3 and two above and below, looking at `centre`."""
  angles = np.arange(8) * np.pi / 4
  eyes = [(3 * np.cos(a), 3 * np.sin(a), 0.4) for a in angles] + [(0.1, 0.0, 3.0),
                                                                   (0.1, 0.0, -3.0)]
  camera_to_world = jnp.stack([camera.look_at(jnp.array(eye, jnp.float32),
                                              jnp.array(centre, jnp.float32)) for eye in eyes])
  return camera.Cameras.create(camera_to_world, focal, width=SIZE, height=SIZE)


def sphere_alphas(cameras, centre=(0.0, 0.0, 0.0)):
  """[N, H, W] the fraction of each pixel's 4 x 4 rays that hit the sphere."""
  alphas = []
  for index in range(cameras.num_cameras):
    hits = []
    for subpixel in camera.subpixel_positions(4):
      rays = camera.image_rays(cameras, index, subpixel=tuple(subpixel))
      offset = np.asarray(rays.origins) - np.asarray(centre)
      along = np.sum(offset * np.asarray(rays.directions), -1)
      closest = np.sum(offset**2, -1) - along**2
      hits.append((closest < BALL_RADIUS**2) & (along < 0))
    alphas.append(np.mean(hits, axis=0))
  return np.stack(alphas).astype(np.float32)


@pytest.fixture(scope="module")
def photographed_sphere():
  cameras = ring_cameras()
  return cameras, sphere_alphas(cameras)


def test_the_hull_keeps_every_cell_the_sphere_touches_and_carves_the_empty_space(
    photographed_sphere):
  cameras, alphas = photographed_sphere
  keep = visual_hull.hull_cells(cameras, alphas, RESOLUTION, from_unit_cube)
  distance = np.linalg.norm(cell_centres(), axis=-1)
  half_diagonal = np.sqrt(3) / RESOLUTION
  assert np.all(keep[distance < BALL_RADIUS + half_diagonal])
  # Ten views bound a sphere by a polyhedron a little larger (the footprints' margins add a
  # cell or two): nothing far from it is kept, and most of the box is carved.
  assert not np.any(keep[distance > 2 * BALL_RADIUS])
  assert keep.mean() < 0.1


def test_an_off_centre_object_keeps_its_cells():
  centre = (0.45, -0.3, 0.2)
  cameras = ring_cameras(centre)
  keep = visual_hull.hull_cells(cameras, sphere_alphas(cameras, centre), RESOLUTION,
                                from_unit_cube)
  distance = np.linalg.norm(cell_centres() - np.asarray(centre), axis=-1)
  assert np.all(keep[distance < BALL_RADIUS + np.sqrt(3) / RESOLUTION])
  assert not np.any(keep[distance > 2 * BALL_RADIUS])


@pytest.mark.parametrize("alpha", [0.0, 1.0])
def test_uniform_photos(photographed_sphere, alpha):
  """Transparent photos carve every cell they see; opaque ones keep all of them (and a cell
  no photo sees is carved)."""
  cameras, alphas = photographed_sphere
  keep = visual_hull.hull_cells(cameras, np.full_like(alphas, alpha), RESOLUTION,
                                from_unit_cube)
  assert keep.mean() == pytest.approx(alpha)


def test_cells_no_photo_sees_are_carved_and_a_frame_edge_does_not_carve():
  """One narrow camera: cells outside its frustum are carved; an opaque photo keeps the cells
  it sees, even those its frame's edge cuts (it cannot show them empty)."""
  cameras = camera.Cameras.create(camera.look_at(jnp.array([0.0, 0.0, 4.0]),
                                                 jnp.zeros(3))[None], 200.0, width=SIZE,
                                  height=SIZE)
  keep = visual_hull.hull_cells(cameras, np.ones((1, SIZE, SIZE), np.float32), RESOLUTION,
                                from_unit_cube)
  pixels, depth = camera.project(cameras, jnp.asarray(cell_centres()))
  pixels = np.asarray(pixels[0])
  in_frame = np.all((pixels >= 0) & (pixels <= SIZE), axis=-1) & (np.asarray(depth[0]) > 0)
  np.testing.assert_array_equal(keep, in_frame)
  assert 0.0 < keep.mean() < 0.5


def test_degenerate_camera_behind_the_cells_judges_nothing(photographed_sphere):
  """A camera inside the box (cells behind it, beside it and a hair in front of it) adds no
  carving where its photo is opaque and never raises."""
  cameras, alphas = photographed_sphere
  inside = camera.Cameras.create(camera.look_at(jnp.array([0.0, 0.0, 0.05]),
                                                jnp.array([0.0, 0.0, 1.0]))[None], 50.0,
                                 width=SIZE, height=SIZE)
  both = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), cameras, inside)
  keep = visual_hull.hull_cells(both, np.concatenate([alphas, np.ones((1, SIZE, SIZE))]),
                                RESOLUTION, from_unit_cube)
  assert np.all(keep[visual_hull.hull_cells(cameras, alphas, RESOLUTION, from_unit_cube)])


def test_carved_cells_stay_carved_and_empty():
  grid = occupancy.initial_grid(4)
  keep = jnp.zeros((4, 4, 4), bool).at[:2].set(True)
  grid = occupancy.carve(grid, keep)
  density = lambda points: jnp.full(points.shape[:1], 100.0)
  for index in range(2):
    grid = occupancy.update(grid, density, jax.random.PRNGKey(index), jnp.int32(index), 32, 0.95)
  np.testing.assert_array_equal(np.asarray(grid[2:]), occupancy.CARVED)
  np.testing.assert_array_equal(np.asarray(grid[:2]), 100.0)
  occupied = occupancy.occupied_cells(grid, step=0.01, min_alpha=0.01)
  np.testing.assert_array_equal(np.asarray(occupied), np.asarray(keep))
  # Unvisited cells count as occupied; carved ones never do.
  fresh = occupancy.carve(occupancy.initial_grid(4), keep)
  np.testing.assert_array_equal(np.asarray(occupancy.occupied_cells(fresh, 0.01, 0.01)),
                                np.asarray(keep))


def test_training_on_photos_with_alpha_carves_what_they_show_empty(sphere):
  """The capture chooses the hull when its photos have alpha (not without, not when told not
  to, never for an edit region); the carved cells stay carved through occupancy refreshes."""
  with_alpha = dataclasses.replace(sphere, alphas=(sphere.depths > 0).astype(np.float32))
  model = small_model(with_alpha)
  trainer = training_run.make_trainer(with_alpha, model=model, config=SMALL_CONFIG)
  assert trainer.config.visual_hull
  trainer.run(until_step=SMALL_CONFIG.occupancy_warmup_steps + 8, progress=False)
  grid = np.asarray(trainer.state.variables["occupancy"])
  carved = grid == occupancy.CARVED
  assert 0.5 < carved.mean() < 1.0
  unit = (np.stack(np.meshgrid(*[np.arange(grid.shape[0])] * 3, indexing="ij"), -1) + 0.5)
  centres = np.asarray(model.from_unit_cube(unit / grid.shape[0]))
  assert not np.any(carved[np.linalg.norm(centres, axis=-1) < SPHERE_RADIUS])
  assert np.isfinite(trainer.last_statistics["loss"])
  told_not_to = training_run.make_trainer(with_alpha, model=model, config=dataclasses.replace(
      SMALL_CONFIG, visual_hull=False))
  without_alpha = training_run.make_trainer(sphere, model=model, config=SMALL_CONFIG)
  for other in (told_not_to, without_alpha):
    assert not np.any(np.asarray(other.state.variables["occupancy"]) == occupancy.CARVED)
  region = dataclasses.replace(model, edit_region=((-0.5,) * 3, (0.5,) * 3))
  assert not capture_choices.with_capture_choices(SMALL_CONFIG, with_alpha, region).visual_hull
