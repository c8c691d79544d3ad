"""The proposal sampler (forward-facing / unbounded scenes) and the appearance embedding."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from small_nerf import SMALL_CONFIG, count_compilations

from signerf_jax import camera
from signerf_jax.nerf import capacity, evaluate, model as nerf_model, scene_info, training_run


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["unbounded", "forward_facing"])
def test_proposal_sampler_trains_without_recompiling(sphere, kind):
  # Forward-facing: the five ring cameras within 45 degrees of the first one's direction.
  views = sphere if kind == "unbounded" else sphere.subset([14, 15, 0, 1, 2])
  dataset = dataclasses.replace(views, scene_kind=kind, background_color=None)
  scene = scene_info.SceneInfo.from_dataset(dataset)
  derived = capacity.derive_capacity(scene, capacity.CapacityRules(samples_per_batch=4096))
  model = nerf_model.NerfModel(scene, dataclasses.replace(derived, proposal_samples=(16, 8),
                                                          samples_per_ray=8, mlp_width=32))
  assert model.capacity.sampler == "proposal" and model.capacity.contract == (kind == "unbounded")
  assert model.capacity.perspective_warp == (kind == "forward_facing")
  trainer = training_run.make_trainer(dataset, model=model, config=SMALL_CONFIG)
  initial = jax.device_get(trainer.state.variables["params"])
  before, _ = evaluate.evaluate(model, trainer.state.variables, dataset.subset([0]))
  trainer.run(until_step=2, progress=False)
  with count_compilations() as compiled:
    trainer.run(until_step=40, progress=False)
  assert compiled == []
  after, renders = evaluate.evaluate(model, trainer.state.variables, dataset.subset([0]))
  assert after["psnr"] > before["psnr"] + 3, (before, after)
  assert all(np.all(np.isfinite(value)) for value in renders.values())
  # Rendering with half the field's samples evaluates only those fewer and still finds the
  # surfaces.
  halved = dataclasses.replace(model, capacity=dataclasses.replace(
      model.capacity, proposal_samples=(32, 16), samples_per_ray=16, render_sample_fraction=0.5))
  rays = jax.tree.map(lambda array: array[:, :4].reshape((-1,) + array.shape[2:]),
                      camera.image_rays(dataset.cameras, 0))
  for training, per_ray in [(False, 32 + 16 + 8), (True, 32 + 16 + 16)]:
    # Jitted: run eagerly, each of its hundreds of operations would compile on its own (~30 s).
    render = jax.jit(lambda variables, rays, training=training: nerf_model.render_rays(
        halved, variables, rays, jax.random.key(0), training=training)[1]["samples_evaluated"])
    assert int(render(trainer.state.variables, rays)) == per_ray * rays.shape[0]
  halved_metrics, _ = evaluate.evaluate(halved, trainer.state.variables, dataset.subset([0]))
  full_metrics, _ = evaluate.evaluate(dataclasses.replace(halved, capacity=dataclasses.replace(
      halved.capacity, render_sample_fraction=1.0)), trainer.state.variables, dataset.subset([0]))
  assert halved_metrics["psnr"] > full_metrics["psnr"] - 1.0, (halved_metrics, full_metrics)
  # The interlevel loss trains every proposal network.
  for name in ("proposal_0", "proposal_1"):
    moved = [not np.array_equal(a, b) for a, b in zip(
        jax.tree.leaves(initial[name]), jax.tree.leaves(trainer.state.variables["params"][name]))]
    assert any(moved), name


def test_appearance_embedding_is_per_image_and_the_mean_for_novel_views(sphere):
  dataset = dataclasses.replace(sphere, scene_kind="unbounded", background_color=None)
  scene = scene_info.SceneInfo.from_dataset(dataset)
  model = nerf_model.NerfModel(scene, capacity.derive_capacity(
      scene, capacity.CapacityRules(appearance_embedding=True)))
  assert model.capacity.appearance_embedding
  variables = nerf_model.init_variables(model, jax.random.PRNGKey(0))
  table = variables["params"]["field"]["appearance"]["embedding"]
  variables["params"]["field"]["appearance"]["embedding"] = jax.random.normal(
      jax.random.PRNGKey(1), table.shape)
  points = jnp.full((3, 3), 0.5)
  directions = jnp.tile(jnp.array([[0.0, 0.0, 1.0]]), (3, 1))
  _, rgb = model.field.apply({"params": variables["params"]["field"]}, points, directions,
                             jnp.array([0, 1, -1]))
  assert not np.allclose(rgb[0], rgb[1])
  # A novel view (-1) uses the mean of the training views' codes.
  codes = variables["params"]["field"]["appearance"]["embedding"]
  mean_table = {**variables["params"]["field"],
                "appearance": {"embedding": jnp.broadcast_to(codes.mean(0), codes.shape)}}
  _, rgb_mean = model.field.apply({"params": mean_table}, points, directions,
                                  jnp.array([0, 1, 2]))
  np.testing.assert_allclose(rgb[2], rgb_mean[2], atol=1e-6)
