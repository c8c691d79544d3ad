"""Rendering trained fields front to back (`nerf.render_trained`, the default of
`render.render_cameras`) against the full render (`settings=None`: every sample, as training
renders), on fields of known shape: an opaque ball (density e^20 times the initial density
inside, e^-10 times outside) written into the coarsest grid level of a small model.

With every shortcut off the two agree to float rounding; with the default settings by at most
the light left at termination, the weight left without its colour and what the proposal
networks' skipped samples move (TOLERANCE), also where rays see nothing, hit an opaque wall at
their first sample, all end early, or meet densities up to float32's largest."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from signerf_jax import camera
from signerf_jax.nerf import front_to_back, render, render_state
from signerf_jax.nerf import model as nerf_model

from small_nerf import count_compilations, small_model

BALL_RADIUS = 0.5  # Scene units, centred at the origin (the analytic sphere's).
# The default settings against the full render: the largest difference of a pixel's colour
# and opacity (termination 1e-2 plus a colour weight of 1e-2 left black, and the proposal's
# skipped samples moving the field's samples a little), and of the mean over the pixels.
TOLERANCE = {"max": 2e-2, "mean": 1e-3}
# Every shortcut off: the same samples, composited in another order.
EXACT = front_to_back.RenderSettings(termination=0.0, colour_weight=0.0,
                                     field_sample_fraction=1.0, empty_below=0.0)
IMAGE_OUTPUTS = ("rgb", "accumulation", "depth", "median_depth", "distance")


def _ball_table(layout, table, inside_radius: float, contract: bool):
  """The flat feature table with the coarsest (dense) level's first feature +1 at vertices
  inside the ball and -1 outside; every other feature 0."""
  resolution = layout.resolutions[0]
  assert layout.dense[0]
  axis = np.arange(resolution + 1) / resolution
  unit = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1)  # [x, y, z, 3]
  # Unit-cube coordinates of the scene's [-1, 1]^3 (contracted: its inner half).
  scene = (unit - 0.5) * (4.0 if contract else 2.0)
  inside = np.linalg.norm(scene, axis=-1) < inside_radius
  rows = np.transpose(inside, (2, 1, 0)).reshape(-1)  # Row x + (N+1) y + (N+1)^2 z.
  new = np.zeros(table.shape, np.float32)
  new[:rows.size, 0] = np.where(rows, 1.0, -1.0)
  return jnp.asarray(new)


def _ball_mlp(dense_0, dense_1, density_shift: float, sharpness: float = 30.0):
  """A density MLP whose output is sharpness relu(feature 0) - 10 + density_shift (other
  outputs: fixed multiples of relu(feature 0), the geometry features)."""
  kernel_0 = np.zeros(dense_0["kernel"].shape, np.float32)
  kernel_0[0, 0] = 1.0
  kernel_1 = np.zeros(dense_1["kernel"].shape, np.float32)
  kernel_1[0] = np.random.default_rng(0).normal(size=kernel_1.shape[1])
  kernel_1[0, 0] = sharpness
  bias_1 = np.zeros(dense_1["bias"].shape, np.float32)
  bias_1[0] = -10.0 + density_shift
  return ({"kernel": jnp.asarray(kernel_0), "bias": jnp.zeros_like(dense_0["bias"])},
          {"kernel": jnp.asarray(kernel_1), "bias": jnp.asarray(bias_1)})


def ball_scene(sphere, kind: str, density_shift: float = 0.0):
  """(model, variables): the opaque ball, its density (log) shifted by `density_shift`; the
  proposal network's ball a little larger and softer (e^2 inside), so that its weights spread
  over the field's surface, as a trained proposal network's do."""
  dataset = sphere if kind == "bounded" else dataclasses.replace(
      sphere, scene_kind=kind, background_color=None)
  model = small_model(dataset)
  model = dataclasses.replace(model, capacity=dataclasses.replace(
      model.capacity, log2_table_size=13))  # The coarsest level dense.
  contract = model.capacity.contract
  variables = nerf_model.init_variables(model, jax.random.PRNGKey(0))
  params = jax.tree.map(jnp.asarray, variables["params"])
  field = params["field"]
  field["encoding"]["table"] = _ball_table(model.field.layout, field["encoding"]["table"],
                                           BALL_RADIUS, contract)
  layers = _ball_mlp(field["density_mlp"]["Dense_0"], field["density_mlp"]["Dense_1"],
                     density_shift)
  field["density_mlp"] = {"Dense_0": layers[0], "Dense_1": layers[1]}
  for index, network in enumerate(model.proposal_fields):
    proposal = params[f"proposal_{index}"]
    proposal["HashGridEncoding_0"]["table"] = _ball_table(
        network.layout, proposal["HashGridEncoding_0"]["table"], BALL_RADIUS * 1.1, contract)
    dense_0, dense_1 = _ball_mlp(proposal["MLP_0"]["Dense_0"], proposal["MLP_0"]["Dense_1"],
                                 density_shift, sharpness=12.0)
    proposal["MLP_0"] = {"Dense_0": dense_0, "Dense_1": dense_1}
  variables = {**variables, "params": params}
  if model.capacity.sampler == "occupancy":
    resolution = variables["occupancy"].shape[0]
    centres = (np.stack(np.meshgrid(*[np.arange(resolution)] * 3, indexing="ij"), -1) + 0.5
               ) / resolution
    variables["occupancy"] = jax.jit(lambda points: nerf_model.field_density(
        model, variables, points))(jnp.asarray(centres, jnp.float32))
  return model, variables


def _hard_rays(sphere) -> camera.Rays:
  """Two views' camera rays, a ray through nothing (beside the ball, out of the scene), one
  starting inside the ball, and one along an axis straight at it."""
  views = [jax.tree.map(lambda a: np.asarray(a).reshape((-1,) + np.asarray(a).shape[2:]),
                        camera.image_rays(sphere.cameras, index)) for index in (0, 5)]
  origins = np.array([[-3.0, 0.9, 0.9], [0.1, 0.0, 0.0], [-3.0, 0.0, 0.0]], np.float32)
  directions = np.array([[1.0, 0.0, 0.0], [0.0, 0.6, 0.8], [1.0, 0.0, 0.0]], np.float32)
  extra = camera.Rays(origins, directions, np.ones(3, np.float32), np.zeros(3, np.int32))
  return jax.tree.map(lambda *parts: np.concatenate(parts), extra, *views)


def _render(model, variables, rays, settings, chunk_size=256):
  return render.render_rays_chunked(model, variables, rays, chunk_size, settings=settings)


def _assert_close(fast, full, tolerance):
  for name in ("rgb", "accumulation"):
    difference = np.abs(fast[name] - full[name])
    assert difference.max() <= tolerance["max"], (name, difference.max())
    assert difference.mean() <= tolerance["mean"], (name, difference.mean())


def _with_fraction(model, fraction):
  return dataclasses.replace(model, capacity=dataclasses.replace(
      model.capacity, render_sample_fraction=fraction))


@pytest.mark.parametrize("kind", ["bounded", "unbounded"])
def test_front_to_back_renders_as_every_sample_does(sphere, kind):
  model, variables = ball_scene(sphere, kind)
  rays = _hard_rays(sphere)
  full = _render(model, variables, rays, None)
  # The ball is seen (2.5 units from the cameras), and the ray through nothing sees nothing:
  # the background, in an unbounded scene the last interval's (to infinity), opaque.
  hit = (full["median_depth"] < 2.5) & (full["accumulation"] > 0.99)
  assert np.sum(hit) > 50
  assert full["accumulation"][0] < 1e-3 if kind == "bounded" else full["median_depth"][0] > 4
  exact = _render(model, variables, rays, EXACT)
  for name in IMAGE_OUTPUTS:
    np.testing.assert_allclose(exact[name], full[name], rtol=1e-5, atol=1e-5, err_msg=name)
  # The defaults, against every sample of as many field samples as they take.
  fraction = render.DEFAULT.field_sample_fraction
  fast = _render(model, variables, rays, render.DEFAULT)
  reference = _render(_with_fraction(model, fraction), variables, rays, None)
  _assert_close(fast, reference, TOLERANCE)
  # The surface is where it was (but where a sample moved across the ball's silhouette).
  moved = np.abs(fast["median_depth"] - reference["median_depth"])[hit]
  assert np.mean(moved < 0.02) > 0.98, np.sort(moved)[-5:]


@pytest.mark.parametrize("density_shift", [30.0, 200.0])
@pytest.mark.parametrize("kind", ["bounded", "unbounded"])
def test_an_opaque_wall_at_the_first_sample_and_huge_densities_stay_finite(sphere, kind,
                                                                             density_shift):
  # Shifted by 30, the density outside the ball is e^20 times the initial one: every ray ends
  # at its first sample (all rays terminate early); by 200 it overflows exp's cap (e^80).
  model, variables = ball_scene(sphere, kind, density_shift)
  rays = _hard_rays(sphere)
  full = _render(model, variables, rays, None)
  fast = _render(model, variables, rays, render.DEFAULT)
  for name in IMAGE_OUTPUTS:
    assert np.all(np.isfinite(fast[name])), name
  exact = _render(model, variables, rays, EXACT)
  for name in ("rgb", "accumulation"):
    np.testing.assert_allclose(exact[name], full[name], atol=1e-5, err_msg=name)
  inside = full["accumulation"] > 0.5  # Rays that start in the scene.
  assert np.mean(inside) > 0.9
  _assert_close(fast, _render(_with_fraction(model, render.DEFAULT.field_sample_fraction),
                              variables, rays, None), TOLERANCE)


@pytest.mark.parametrize("list_samples, overflow_share", [(8, 0.5), (8, 1e-3)])
def test_rays_overflowing_their_lists_are_marched_again(sphere, list_samples, overflow_share):
  # A list of one block of steps is too short for rays crossing the ball's fog-free front
  # (the ball's density shifted down to a haze); they are marched again, a few at a time or
  # (more than the share) the whole chunk, and render as every sample does.
  model, variables = ball_scene(sphere, "bounded", density_shift=-19.0)
  rays = _hard_rays(sphere)
  settings = dataclasses.replace(EXACT, list_samples=list_samples,
                                 overflow_share=overflow_share)
  full = _render(model, variables, rays, None)
  assert 0.05 < np.max(full["accumulation"]) < 0.99  # A haze: no ray ends early.
  listed = _render(model, variables, rays, settings)
  for name in IMAGE_OUTPUTS:
    np.testing.assert_allclose(listed[name], full[name], rtol=1e-5, atol=1e-5, err_msg=name)


def test_the_proposal_density_grid_bounds_the_density_it_skips(sphere):
  model, variables = ball_scene(sphere, "unbounded")
  grid = np.asarray(render_state.skipping(model, variables)["proposal"][0])
  resolution = grid.shape[0]
  points = jax.random.uniform(jax.random.PRNGKey(1), (20000, 3))
  density = np.asarray(model.proposal_fields[0].apply(
      {"params": variables["params"]["proposal_0"]}, points))
  cells = np.minimum((np.asarray(points) * resolution).astype(int), resolution - 1)
  assert np.all(density <= grid[cells[:, 0], cells[:, 1], cells[:, 2]] * (1 + 1e-5))


@pytest.mark.parametrize("kind", ["bounded", "unbounded"])
def test_other_ray_counts_reuse_the_compilation(sphere, kind):
  model, variables = ball_scene(sphere, kind)
  rays = _hard_rays(sphere)
  _render(model, variables, jax.tree.map(lambda a: a[:700], rays), render.DEFAULT)
  with count_compilations() as compiled:
    _render(model, variables, jax.tree.map(lambda a: a[:1000], rays), render.DEFAULT)
    _render(model, variables, jax.tree.map(lambda a: a[:300], rays), render.DEFAULT)
  assert not compiled
