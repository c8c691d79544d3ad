"""Edit regions: a trained field inside a box, composited over the frozen original field.

The merge of two fields' samples (`volume.merge_samples`) against closed forms, on the hard
cases (rays missing the region, a region spanning the whole ray, zero and huge densities); and
a model with an edit region trained on the sphere scene: rays missing the box render as the
original does (to float rounding), the original stays frozen, nothing recompiles, and a saved
run loads back.
"""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from small_nerf import SMALL_CONFIG, count_compilations, small_model

from signerf_jax import camera
from signerf_jax.editing import finetune
from signerf_jax.editing.config import FinetuneConfig
from signerf_jax.errors import InputError
from signerf_jax.nerf import (capacity, edit_region_render, evaluate, render, render_trained,
                              sampling, scene_info, train, training_data, training_run, volume)
from signerf_jax.nerf import model as nerf_model

BACKGROUND = jnp.array([0.2, 0.4, 0.6])
OUTER_COLOR, INNER_COLOR = 0.25, 0.75


def constant_field(start, stop, intervals, density, color):
  """One ray's samples of a field of constant density and grey level on [start, stop]."""
  edges = jnp.linspace(start, stop, intervals + 1)[None]
  return (jnp.full((1, intervals), density, jnp.float32),
          jnp.full((1, intervals, 3), color, jnp.float32), edges)


def merged_render(outer_density, inner_density, t_in, t_out, inner_range=None):
  outer = constant_field(0.0, 10.0, 10, outer_density, OUTER_COLOR)
  inner = constant_field(*(inner_range or (t_in, t_out)), 7, inner_density, INNER_COLOR)
  samples = volume.merge_samples(outer, inner, jnp.array([t_in]), jnp.array([t_out]))
  return volume.volume_render(*samples, jnp.ones(1), BACKGROUND), samples


@pytest.mark.parametrize("outer_density", [0.0, 0.1, 1e10])
@pytest.mark.parametrize("inner_density", [0.0, 0.3, 1e10])
@pytest.mark.parametrize("t_in, t_out", [(3.0, 5.5), (0.0, 10.0), (2.5, 2.5), (10.0, 10.0)])
def test_merged_samples_match_the_closed_form(outer_density, inner_density, t_in, t_out):
  outputs, _ = merged_render(outer_density, inner_density, t_in, t_out)
  # Piecewise constant densities: light passes [0, t_in] and [t_out, 10] of the outer field,
  # [t_in, t_out] of the inner one.
  before, inside, after = t_in, t_out - t_in, 10.0 - t_out
  transmit = lambda density, length: np.exp(-min(density * length, 1e6))
  through_before = transmit(outer_density, before)
  through_inside = transmit(inner_density, inside)
  expected = ((1 - through_before) * OUTER_COLOR
              + through_before * (1 - through_inside) * INNER_COLOR
              + through_before * through_inside * (1 - transmit(outer_density, after))
              * OUTER_COLOR
              + through_before * through_inside * transmit(outer_density, after)
              * np.asarray(BACKGROUND))
  np.testing.assert_allclose(outputs["rgb"][0], expected, atol=1e-5)


@pytest.mark.parametrize("inner_density", [0.0, 1e-6, 1.0, 1e10])
def test_merge_gradients_are_finite_and_reach_only_the_inner_field_inside(inner_density):
  outer = constant_field(0.0, 10.0, 10, 0.05, OUTER_COLOR)
  inner = constant_field(3.0, 5.5, 5, inner_density, INNER_COLOR)
  t_in, t_out = jnp.array([3.0]), jnp.array([5.5])

  def rendered(outer_fields, inner_fields):
    samples = volume.merge_samples((*outer_fields, outer[2]), (*inner_fields, inner[2]), t_in,
                                   t_out)
    return jnp.sum(volume.volume_render(*samples, jnp.ones(1), BACKGROUND)["rgb"])

  outer_gradients, inner_gradients = jax.grad(rendered, argnums=(0, 1))(outer[:2], inner[:2])
  for gradient in jax.tree.leaves((outer_gradients, inner_gradients)):
    assert np.all(np.isfinite(gradient))
  # Outer intervals 3 and 4 ([3, 4], [4, 5]) lie inside the region: they cannot matter.
  np.testing.assert_array_equal(outer_gradients[0][0, 3:5], 0.0)
  assert any(np.any(gradient != 0) for gradient in inner_gradients)


def test_a_ray_missing_the_region_keeps_the_outer_fields_samples_exactly():
  outer = constant_field(0.0, 10.0, 10, 0.2, OUTER_COLOR)
  alone = volume.volume_render(*outer, jnp.ones(1), BACKGROUND)
  outputs, samples = merged_render(0.2, 1e10, 10.0, 10.0)
  for name in ("rgb", "accumulation", "depth", "median_depth"):
    np.testing.assert_array_equal(outputs[name], alone[name], err_msg=name)
  assert samples[2].shape == (1, 11 + 8 + 2)


# ------------------------------------------------------------------------------------------------
# A model with an edit region on the sphere scene.

REGION = ((0.0, -0.6, -0.6), (0.6, 0.6, 0.6))  # The sphere's +x half (radius 0.5).
RED = np.array([1.0, 0.0, 0.0], np.float32)


@pytest.fixture(scope="module")
def edited(sphere):
  """The original NeRF (briefly trained) and an edit region trained on red-sphere images."""
  model = small_model(sphere)
  original = training_run.make_trainer(sphere, model=model, config=SMALL_CONFIG)
  original.run(until_step=60, progress=False)
  original_variables = jax.device_get(original.state.variables)
  red = dataclasses.replace(sphere, images=np.where(sphere.depths[..., None] > 0, RED,
                                                    sphere.images))
  region_model = dataclasses.replace(model, edit_region=REGION)
  trainer = training_run.make_trainer(red, model=region_model, config=SMALL_CONFIG,
                                      init_variables={"original": original_variables})
  trainer.run(until_step=40, progress=False)
  return model, original_variables, trainer


def region_hits(cameras, index):
  rays = camera.image_rays(cameras, index)
  _, _, hit = sampling.intersect_aabb(rays.origins, rays.directions,
                                      np.asarray(REGION, np.float32))
  return np.asarray(hit)


@pytest.mark.slow
def test_only_the_region_changes_and_the_original_stays_frozen(sphere, edited):
  model, original_variables, trainer = edited
  cameras = sphere.cameras.take([0, 4])
  before = render.render_cameras(model, original_variables, cameras)
  after = render.render_cameras(trainer.model, trainer.state.variables, cameras)
  for view in range(2):
    missed = ~region_hits(cameras, view)
    assert missed.any() and (~missed).any()
    np.testing.assert_allclose(after["rgb"][view][missed], before["rgb"][view][missed],
                               atol=1e-6)
    np.testing.assert_allclose(after["depth"][view][missed], before["depth"][view][missed],
                               rtol=1e-5)
    inside = ~missed & (sphere.depths[[0, 4]][view] > 0)
    red = after["rgb"][view][inside].mean(0)
    assert red[0] > 0.8 and red[1:].max() < 0.3, red
  for kept, given in zip(jax.tree.leaves(trainer.state.variables["original"]),
                         jax.tree.leaves(original_variables)):
    np.testing.assert_array_equal(kept, given)


@pytest.mark.slow
def test_training_an_edit_region_compiles_once(sphere, edited):
  _, _, trainer = edited
  trainer.run(until_step=trainer.step + 5, progress=False)
  with count_compilations() as compiled:
    trainer.run(until_step=trainer.step + 4, progress=False)
  assert compiled == []
  assert np.isfinite(trainer.last_statistics["loss"])


@pytest.mark.slow
def test_an_edit_region_run_saves_and_loads_back(sphere, edited, tmp_path):
  model, original_variables, trainer = edited
  training_run.write_model_file(tmp_path, trainer.model, sphere)
  trainer.save(tmp_path)
  loaded = evaluate.load_run(tmp_path)
  assert loaded.model == trainer.model and loaded.model.edit_region == REGION
  cameras = sphere.cameras.take([2])
  np.testing.assert_array_equal(
      render.render_cameras(loaded.model, loaded.variables, cameras)["rgb"],
      render.render_cameras(trainer.model, trainer.state.variables, cameras)["rgb"])
  description = json.loads((tmp_path / training_run.MODEL_FILE).read_text())
  description["edit_region"] = [[0, 0, 0], [0, 1, 1]]
  (tmp_path / training_run.MODEL_FILE).write_text(json.dumps(description))
  with pytest.raises(InputError, match="model.json"):
    training_run.read_model_file(tmp_path)


@pytest.mark.slow
def test_a_diffuse_edit_region_colours_alike_from_every_direction(sphere, tmp_path):
  model = dataclasses.replace(small_model(sphere), edit_region=REGION,
                              region_view_dependence=False)
  variables = nerf_model.init_variables(model, jax.random.key(0))
  points = jnp.full((4, 3), 0.6, jnp.float32)
  directions = jnp.asarray([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -1]], jnp.float32)
  colours = lambda model, params: np.asarray(model.field.apply({"params": params["field"]},
                                                                points, directions)[1])
  diffuse = colours(model, variables["params"])
  np.testing.assert_allclose(diffuse, np.broadcast_to(diffuse[:1], diffuse.shape), atol=1e-6)
  # The original field underneath keeps its view dependence (and its parameters' shapes).
  view_dependent = colours(model.original, variables["original"]["params"])
  assert np.abs(view_dependent - view_dependent[:1]).max() > 1e-4
  training_run.write_model_file(tmp_path, model, sphere)
  assert training_run.read_model_file(tmp_path)[0] == model
  description = json.loads((tmp_path / training_run.MODEL_FILE).read_text())
  description["region_view_dependence"] = "false"
  (tmp_path / training_run.MODEL_FILE).write_text(json.dumps(description))
  with pytest.raises(InputError, match="region_view_dependence"):
    training_run.read_model_file(tmp_path)


@pytest.mark.slow
def test_the_proposal_sampler_keeps_rays_missing_the_region_too(sphere):
  region_model, region_variables = proposal_region_model(sphere)
  cameras = sphere.cameras.take([1])
  before = render.render_cameras(region_model.original, region_variables["original"],
                                 cameras)["rgb"][0]
  after = render.render_cameras(region_model, region_variables, cameras)["rgb"][0]
  missed = ~region_hits(cameras, 0)
  np.testing.assert_allclose(after[missed], before[missed], atol=1e-6)
  assert not np.allclose(after[~missed], before[~missed])


def proposal_region_model(sphere):
  """An unbounded proposal-sampler model of the sphere scene with the edit region, untrained."""
  dataset = dataclasses.replace(sphere, scene_kind="unbounded", background_color=None)
  scene = scene_info.SceneInfo.from_dataset(dataset)
  derived = capacity.derive_capacity(scene, capacity.CapacityRules(samples_per_batch=4096))
  model = nerf_model.NerfModel(scene, dataclasses.replace(derived, proposal_samples=(16, 8),
                                                          samples_per_ray=8, mlp_width=32),
                               edit_region=REGION)
  return model, {**nerf_model.init_variables(model, jax.random.PRNGKey(1)),
                 "original": nerf_model.init_variables(model.original, jax.random.PRNGKey(0))}


@pytest.mark.slow
@pytest.mark.parametrize("sampler", ["occupancy", "proposal"])
def test_precomputed_surroundings_render_as_the_merged_fields(sphere, edited, sampler):
  """Training renders the trained field between the original's precomputed render in front of
  and behind the region: the same image as merging both fields' samples, for rays that cross
  the region, start inside it or miss it."""
  if sampler == "occupancy":
    model, variables = edited[2].model, edited[2].state.variables
  else:
    model, variables = proposal_region_model(sphere)
  rays = jax.tree.map(lambda array: array.reshape(-1, *array.shape[2:]),
                      camera.image_rays(sphere.cameras, 3))
  inside_origin = jax.tree.map(lambda array: array[:4], rays).replace(
      origins=jnp.tile(jnp.array([[0.3, 0.0, 0.0]]), (4, 1)))
  rays = jax.tree.map(lambda *arrays: jnp.concatenate(arrays), rays, inside_origin)

  # Jitted: eagerly, each of their operations would compile on its own (~10 s).
  @jax.jit
  def both_ways(variables, rays):
    surroundings = nerf_model.region_surroundings(model, variables, rays)
    key = jax.random.PRNGKey(0)
    merged, _ = nerf_model.render_rays(model, variables, rays, key, training=False)
    split, _ = nerf_model.render_rays(model, variables, rays, key, training=False,
                                      surroundings=surroundings)
    return surroundings, merged, split

  surroundings, merged, split = both_ways(variables, rays)
  crossing = np.asarray(surroundings.t_out > surroundings.t_in)
  assert crossing.any() and (~crossing).any() and crossing[-4:].all()
  for name in ("rgb", "accumulation"):
    np.testing.assert_allclose(split[name], merged[name], atol=2e-5, err_msg=name)


@pytest.mark.slow
def test_an_edit_region_trains_only_on_the_pixels_whose_rays_cross_it(sphere, edited):
  model, variables = edited[2].model, edited[2].state.variables
  weights = np.ones(sphere.images.shape[:3], np.float32)
  weights[1] = 0.0
  data = training_data.TrainingData.from_dataset(sphere, weights)
  region = training_data.with_region_rays(data, model, variables, chunk_size=1000).region
  crossing = np.stack([region_hits(sphere.cameras, view) for view in range(len(weights))])
  crossing[1] = False
  np.testing.assert_array_equal(np.sort(np.asarray(region.pixels)), np.flatnonzero(crossing))
  _, (index, row, column), surroundings = training_data.sample_rays(jax.random.PRNGKey(3),
                                                            data.replace(region=region), 512)
  assert crossing[index, row, column].all()
  assert surroundings.t_in.shape == (512,)


@pytest.mark.slow
def test_an_edit_region_no_training_pixel_sees_is_an_error(sphere, edited):
  model = dataclasses.replace(edited[2].model, edit_region=((2.0, 2.0, 2.0), (2.5, 2.5, 2.5)))
  with pytest.raises(InputError, match="no training pixel sees the edit region"):
    training_data.with_region_rays(training_data.TrainingData.from_dataset(sphere), model,
                           edited[2].state.variables)


@pytest.mark.slow
@pytest.mark.parametrize("entropy_weight", [0.0, 0.05])
def test_fine_tuning_an_edit_region_learns_it_with_or_without_the_opacity_prior(
    sphere, edited, tmp_path, entropy_weight):
  model, original_variables, _ = edited
  region_model = dataclasses.replace(model, edit_region=REGION)
  red = dataclasses.replace(sphere, images=np.where(sphere.depths[..., None] > 0, RED,
                                                    sphere.images))
  trainer = finetune.finetune(red, tmp_path, model=region_model,
                              init_variables={"params": original_variables["params"],
                                              "original": original_variables},
                              config=dataclasses.replace(SMALL_CONFIG, steps=40,
                                                         opacity_entropy_weight=entropy_weight),
                              loss_settings=finetune.FinetuneLosses(), edited_bounds=REGION,
                              progress=False)
  statistics = trainer.last_statistics
  assert np.isfinite(statistics["loss"])
  assert ("opacity_entropy" in statistics) == (entropy_weight > 0)
  if entropy_weight:
    assert statistics["loss"] >= statistics["l1"] + entropy_weight * statistics["opacity_entropy"]
  cameras = sphere.cameras.take([0])
  after = render.render_cameras(trainer.model, trainer.state.variables, cameras)["rgb"][0]
  inside = region_hits(cameras, 0) & (sphere.depths[0] > 0)
  assert after[inside].mean(0)[0] > 0.7
  with count_compilations() as compiled:
    trainer.run(until_step=trainer.step + 3, progress=False)
  assert compiled == []


@pytest.mark.parametrize("region", [((0, 0, 0), (0, 1, 1)), ((1, 1, 1), (0, 0, 0))])
def test_an_empty_region_is_an_error(sphere, region):
  with pytest.raises(InputError, match="edit region"):
    dataclasses.replace(small_model(sphere), edit_region=region)


def test_original_variables_need_an_edit_region(sphere):
  model = small_model(sphere)
  variables = nerf_model.init_variables(model, jax.random.PRNGKey(0))
  with pytest.raises(InputError, match="without an edit region"):
    train.init_state(model, SMALL_CONFIG, {"params": variables["params"], "original": variables})


def test_a_negative_region_margin_is_an_error_naming_the_setting():
  with pytest.raises(InputError, match="FinetuneConfig.region_margin"):
    FinetuneConfig(region_margin=-0.1)


@pytest.mark.parametrize("supersampling", [1, 2])
def test_region_pixels_are_those_whose_rays_cross_the_region(sphere, supersampling):
  region_model, _ = proposal_region_model(sphere)
  cameras = sphere.cameras.take([1, 3])
  pixels = edit_region_render.region_pixels(region_model, cameras, supersampling)
  for view in range(2):
    centres = region_hits(cameras, view)
    assert centres.any() and (~centres).any()
    if supersampling == 1:
      np.testing.assert_array_equal(pixels[view], centres)
    else:  # A pixel any of whose four rays crosses: the centres' pixels and a rim around them.
      assert pixels[view][centres].all() and pixels[view].sum() > centres.sum()


def test_the_edited_render_over_the_original_equals_a_full_render(sphere):
  region_model, region_variables = proposal_region_model(sphere)
  cameras = sphere.cameras.take([1, 3])
  original = render.render_cameras(region_model.original, region_variables["original"],
                                   cameras)["rgb"]
  full = render.render_cameras(region_model, region_variables, cameras)["rgb"]
  composed = edit_region_render.render_over_original(region_model, region_variables, cameras,
                                                     original)
  np.testing.assert_allclose(composed, full, atol=1e-6)
  assert not np.allclose(composed, original, atol=1e-3)  # The region did change something.


def test_the_edited_render_over_the_original_skips_the_front_to_back_renderer(sphere,
                                                                               monkeypatch):
  # Its rays all cross the region, rendered with every sample either way: compiling the
  # original's front-to-back renderer for them would be time lost.
  region_model, region_variables = proposal_region_model(sphere)
  cameras = sphere.cameras.take([1])

  def front_to_back(*args, **kwargs):
    raise AssertionError("the front-to-back renderer was traced")

  monkeypatch.setattr(render_trained, "render_rays", front_to_back)
  render._render_chunk.clear_cache()  # Traced anew, not taken from an earlier test's program.
  original = np.zeros((1, cameras.height, cameras.width, 3), np.float32)
  composed = edit_region_render.render_over_original(region_model, region_variables, cameras,
                                                     original)
  assert not np.allclose(composed, original)


def test_an_edited_render_splits_its_rays_as_one_program_would(sphere, monkeypatch):
  # render_rays_chunked renders the rays that miss the region with the original's own program
  # and those that cross it with every sample; render_chunks does both within one program.
  region_model, region_variables = proposal_region_model(sphere)
  rays = jax.tree.map(lambda a: np.asarray(a).reshape((-1,) + np.asarray(a).shape[2:]),
                      render.image_rays(sphere.cameras, 1))
  crossing = np.asarray(nerf_model.crosses_region(region_model, rays))
  assert crossing.any() and (~crossing).any()
  box = np.array([[-0.3, -0.3, -0.3], [0.3, 0.3, 0.3]], np.float32)
  render.render_rays_chunked(region_model.original, region_variables["original"], rays)

  def front_to_back(*args, **kwargs):
    raise AssertionError("the front-to-back renderer was traced again")

  with monkeypatch.context() as patch:  # The original's program serves the missing rays.
    patch.setattr(render_trained, "render_rays", front_to_back)
    split = render.render_rays_chunked(region_model, region_variables, rays, selection_box=box)
  together = render.assemble(render.render_chunks(region_model, region_variables, rays,
                                                  selection_box=box), rays.shape)
  for name in render.IMAGE_OUTPUTS:
    np.testing.assert_allclose(split[name], together[name], atol=1e-5, err_msg=name)


def test_an_edit_region_out_of_view_renders_nothing_again(sphere, monkeypatch):
  region_model, region_variables = proposal_region_model(sphere)
  cameras = sphere.cameras.take([0])
  rays, centre = camera.image_rays(cameras, 0), (cameras.height // 2, cameras.width // 2)
  behind = np.asarray(rays.origins[centre] - 2.0 * rays.directions[centre])
  behind_the_cameras = dataclasses.replace(
      region_model, edit_region=(tuple(behind - 0.1), tuple(behind + 0.1)))
  rendered_pixels = []
  full_render = render.render_cameras

  def counting_render(*args, pixels=None, **kwargs):
    rendered_pixels.append(None if pixels is None else int(np.sum(pixels)))
    return full_render(*args, pixels=pixels, **kwargs)

  monkeypatch.setattr(render, "render_cameras", counting_render)
  original = np.full((1, cameras.height, cameras.width, 3), 0.3, np.float32)
  composed = edit_region_render.render_over_original(behind_the_cameras, region_variables,
                                                     cameras, original)
  np.testing.assert_array_equal(composed, original)
  assert rendered_pixels == [0]
  edit_region_render.render_over_original(behind_the_cameras.original,
                                          region_variables["original"], cameras, original)
  assert rendered_pixels == [0, None]  # Without an edit region: every pixel.
