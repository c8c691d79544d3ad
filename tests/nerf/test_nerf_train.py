import dataclasses

import jax
import numpy as np
import pytest
from small_nerf import SMALL_CONFIG, count_compilations, small_model

from signerf_jax import checkpoints, ownership, training_loop
from signerf_jax.nerf import evaluate, keypoint_depth, render, train, training_data, training_run
from signerf_jax.nerf import model as nerf_model
from signerf_jax.training_loop import TrainingDiverged


@pytest.fixture(scope="module")
def trained(sphere, tmp_path_factory):
  """A small model trained briefly on the sphere, with its PSNR before training."""
  model = small_model(sphere)
  trainer = training_run.make_trainer(sphere, model=model, config=SMALL_CONFIG)
  before, _ = evaluate.evaluate(model, trainer.state.variables, sphere.subset([0, 5]))
  trainer.run(until_step=120, progress=False)
  return trainer, before


def test_training_raises_psnr_and_learns_depth(sphere, trained):
  trainer, before = trained
  after, renders = evaluate.evaluate(trainer.model, trainer.state.variables, sphere.subset([0, 5]))
  assert after["psnr"] > before["psnr"] + 8, (before, after)
  assert after["ssim"] > before["ssim"]
  # Depth moves towards the sphere's surface (ground truth 2.0 to 2.2 in these views); after so
  # few steps the surface is still soft, so its expected depth lies a little behind it.
  assert after["depth_mae"] < min(0.2, before["depth_mae"]), (before, after)
  assert renders["rgb"].shape == (2, 24, 24, 3) and renders["depth"].shape == (2, 24, 24)
  background = sphere.depths[[0, 5]] == 0
  assert np.mean(renders["accumulation"][background]) < 0.2


@pytest.mark.slow
def test_second_training_step_and_second_render_compile_nothing(sphere, trained):
  trainer, _ = trained
  trainer.run(until_step=trainer.step + 1, progress=False)  # an occupancy update is due here or
  trainer.run(until_step=trainer.step + 4, progress=False)  # among these steps
  with count_compilations() as compiled:
    trainer.run(until_step=trainer.step + 4, progress=False)
  assert compiled == []
  cameras = sphere.cameras.take([1])
  render.render_cameras(trainer.model, trainer.state.variables, cameras, chunk_size=256)
  with count_compilations() as compiled:
    render.render_cameras(trainer.model, trainer.state.variables, cameras, chunk_size=256)
  assert compiled == []


@pytest.mark.slow
@pytest.mark.parametrize("sampler", ["occupancy", "proposal"])
def test_fresh_variables_are_one_compiled_program(sphere, sampler):
  # Eagerly, each of the initialisers' small operations compiled on its own (83-93 programs
  # here); jitted, the first call compiles at most once and a second not at all.
  model = small_model(dataclasses.replace(
      sphere, scene_kind="bounded" if sampler == "occupancy" else "unbounded"))
  assert model.capacity.sampler == sampler
  key = jax.random.PRNGKey(3)
  with count_compilations() as compiled:
    first = nerf_model.init_variables(model, key)
  assert len(compiled) <= 1
  with count_compilations() as compiled:
    second = nerf_model.init_variables(model, key)
  assert compiled == []
  assert jax.tree.all(jax.tree.map(np.array_equal, first, second))


def test_resumed_run_equals_uninterrupted_run(sphere, tmp_path):
  model = small_model(sphere)
  config = dataclasses.replace(SMALL_CONFIG, steps=10)
  uninterrupted = training_run.train(sphere, tmp_path / "whole", model=model, config=config,
                                     progress=False)
  # The first half stops at step 5 of the same 10-step run (same learning-rate schedule).
  first_half = training_run.make_trainer(sphere, model=model, config=config)
  with ownership.claimed(tmp_path / "split", ownership.RUN):  # As `training_run.train` does.
    training_run.write_model_file(tmp_path / "split", model, sphere)
    first_half.run(until_step=5, run_dir=tmp_path / "split", progress=False)
  resumed = training_run.train(sphere, tmp_path / "split", config=config, progress=False)
  assert resumed.step == uninterrupted.step == 10
  whole_leaves = jax.tree.leaves(uninterrupted.state)
  split_leaves = jax.tree.leaves(resumed.state)
  assert len(whole_leaves) == len(split_leaves)
  for whole, split in zip(whole_leaves, split_leaves):
    np.testing.assert_allclose(np.asarray(whole), np.asarray(split), rtol=1e-6, atol=1e-7)


def test_interrupted_run_keeps_its_last_checkpoint(sphere, tmp_path):
  model = small_model(sphere)
  config = dataclasses.replace(SMALL_CONFIG, steps=10, checkpoint_every_steps=3)
  trainer = training_run.make_trainer(sphere, model=model, config=config)
  step_fn = trainer._step_fn

  def failing_step(state, data, progress):
    if int(state.step) == 7:
      raise KeyboardInterrupt
    return step_fn(state, data, progress)

  trainer._step_fn = failing_step
  with ownership.claimed(tmp_path, ownership.RUN):  # As `training_run.train` does.
    training_run.write_model_file(tmp_path, model, sphere)
    with pytest.raises(training_loop.TrainingInterrupted) as interrupted:
      trainer.run(run_dir=tmp_path, progress=False)
  restored, metadata = checkpoints.restore(tmp_path, train.init_state(model, config))
  # The 7 steps done are saved, not only the 6 of the last periodic checkpoint.
  assert int(restored.step) == metadata["step"] == interrupted.value.step == 7
  assert not list(tmp_path.glob(".checkpoint*"))  # no temporary file left behind


@pytest.mark.slow
def test_fine_tuning_starts_from_given_variables_and_honours_pixel_weights(sphere, trained,
                                                                           tmp_path):
  trainer, _ = trained
  variables = jax.device_get(trainer.state.variables)
  ignored = training_run.train(sphere, tmp_path / "ignored", init_variables=variables,
                               model=trainer.model, config=SMALL_CONFIG, steps=3,
                               pixel_weights=np.zeros(sphere.images.shape[:3]),
                               progress=False)
  for before, after in zip(jax.tree.leaves(variables["params"]),
                           jax.tree.leaves(ignored.state.variables["params"])):
    np.testing.assert_array_equal(before, after)
  # The old occupancy grid is dropped: edits may add content where the scene was empty.
  assert np.any(variables["occupancy"] >= 0)
  assert np.all(np.asarray(ignored.state.variables["occupancy"]) < 0)
  weighted = training_run.train(sphere, tmp_path / "weighted", init_variables=variables,
                                model=trainer.model, config=SMALL_CONFIG, steps=3,
                                progress=False)
  changed = [not np.array_equal(before, after) for before, after in zip(
      jax.tree.leaves(variables["params"]), jax.tree.leaves(weighted.state.variables["params"]))]
  assert all(changed)
  loaded = evaluate.load_run(tmp_path / "weighted")
  assert loaded.model == trainer.model and loaded.step == 3


@pytest.mark.slow
def test_a_time_budget_is_what_the_schedule_spans(sphere):
  """With max_seconds, progress is the larger of the steps and the seconds fractions, so a run
  stopped by its time budget ends annealed although it did few of its steps."""
  # Occupancy refreshes from the first step: every compilation happens in the first step, so no
  # later step is slow enough to leave the schedule short of its end (one at step 32 was). No
  # warm-up: on a busy machine 3 s may hold fewer than its 50 steps.
  config = dataclasses.replace(SMALL_CONFIG, steps=1_000_000, max_seconds=3.0,
                               occupancy_warmup_steps=0, warmup_steps=0)
  trainer = training_run.make_trainer(sphere, model=small_model(sphere), config=config)
  trainer.seconds_trained = 1.5
  assert trainer.progress == pytest.approx(0.5)
  trainer.seconds_trained = 0.0
  statistics = trainer.run(progress=False)
  assert trainer.seconds_trained >= 3.0 and trainer.step < 1000
  assert trainer.progress == 1.0
  # The last step ran at the end of the schedule (within one step's share of the time).
  final = trainer.config.final_learning_rate
  assert final <= statistics["learning_rate"] <= final * (trainer.config.learning_rate / final)**(
      2 * (trainer.seconds_trained / trainer.step) / 3.0)


def test_a_diverged_run_stops_and_keeps_its_last_good_checkpoint(sphere, tmp_path):
  model = small_model(sphere)
  config = dataclasses.replace(SMALL_CONFIG, steps=20, checkpoint_every_steps=1)
  trainer = training_run.make_trainer(sphere, model=model, config=config)
  trainer.run(until_step=3, run_dir=tmp_path, progress=False)
  # NaN targets make the loss NaN from the next step on.
  trainer.data = trainer.data.replace(images=trainer.data.images * np.float32("nan"))
  with pytest.raises(TrainingDiverged, match="after step 4.*learning_rate") as error:
    trainer.run(until_step=10, run_dir=tmp_path, progress=False)
  assert error.value.path == str(tmp_path)
  state, metadata = checkpoints.restore(tmp_path, trainer.state)
  assert metadata["step"] == int(state.step) == 3
  assert all(np.isfinite(leaf).all() for leaf in jax.tree.leaves(state.variables["params"]))


def test_selection_weight_is_the_opacity_inside_the_box(sphere, trained):
  trainer, _ = trained
  cameras = sphere.cameras.take([2])

  def weight(box):
    return render.render_cameras(trainer.model, trainer.state.variables, cameras, chunk_size=256,
                                 selection_box=box)

  everything = weight(np.array([[-9.0] * 3, [9.0] * 3]))
  np.testing.assert_allclose(everything["selection_weight"], everything["accumulation"],
                             atol=1e-5)
  assert np.all(weight(None)["selection_weight"] == 0.0)
  # The sphere's half at x > 0: less weight than the whole, and none on rays that miss it.
  with count_compilations() as compiled:
    half = weight(np.array([[0.0, -9.0, -9.0], [9.0, 9.0, 9.0]]))["selection_weight"]
  assert compiled == []
  assert np.all(half <= everything["accumulation"] + 1e-6)
  assert 0.05 < half.sum() / everything["accumulation"].sum() < 0.95
  misses = sphere.depths[2] == 0
  assert np.mean(half[0][misses]) < 0.1


@pytest.mark.slow
def test_a_sparse_capture_trains_and_renders_each_pixel_as_the_mean_of_four_rays(sphere):
  """Eight views: the derived model fits each photo's pixel with the mean of 2 x 2 rays inside
  it, learns the sphere that way, and renders (and is evaluated) 2 x 2 rays a pixel."""
  sparse = sphere.subset(list(range(0, 16, 2)))
  model = training_run.build_model(sparse)
  assert model.capacity.pixel_samples == 2
  model = dataclasses.replace(model, capacity=dataclasses.replace(
      model.capacity, rays_per_batch=1024, samples_per_batch=8192, mlp_width=32))
  trainer = training_run.make_trainer(sparse, model=model, config=SMALL_CONFIG)
  views = sphere.subset([1, 6])  # Between the training views.
  before, _ = evaluate.evaluate(model, trainer.state.variables, views)
  trainer.run(until_step=100, progress=False)
  after, _ = evaluate.evaluate(model, trainer.state.variables, views)
  assert after["supersampling"] == 2
  assert after["psnr"] > before["psnr"] + 6, (before, after)
  centre, _ = evaluate.evaluate(model, trainer.state.variables, views, supersampling=1)
  assert centre["supersampling"] == 1 and centre["psnr"] != after["psnr"]
  with count_compilations() as compiled:
    trainer.run(until_step=102, progress=False)
  assert not compiled


@pytest.mark.slow
def test_the_opacity_prior_is_part_of_the_training_loss_when_weighted(sphere):
  model = small_model(sphere)
  config = dataclasses.replace(SMALL_CONFIG, opacity_entropy_weight=0.5)
  state = train.init_state(model, config)
  # Jitted: eagerly, each operation of the step and its gradient would compile on its own.
  step = jax.jit(train.train_step, static_argnums=(0, 1))
  _, statistics = step(model, config, state, training_data.TrainingData.from_dataset(sphere),
                       np.float32(0.5))
  entropy = float(statistics["opacity_entropy"])
  assert 0 < entropy <= np.log(2) + 1e-6
  mse = 10 ** (-float(statistics["psnr"]) / 10)
  assert float(statistics["loss"]) >= mse + 0.5 * entropy - 1e-6


@pytest.mark.slow
def test_keypoint_depth_is_part_of_the_training_loss_and_its_gradients_finite(sphere):
  model = small_model(sphere)
  # A budget every ray fits (the untrained grid samples everywhere; the keypoint rays come last).
  model = dataclasses.replace(model, capacity=dataclasses.replace(model.capacity,
                                                                  samples_per_batch=65536))
  config = dataclasses.replace(SMALL_CONFIG, keypoint_depth_weight=5.0, keypoint_rays=8)
  keypoints = keypoint_depth.KeypointDepths(np.array([0, 3], np.int32),
                                            np.array([[12.5, 12.5], [3.5, 20.5]], np.float32),
                                            np.array([1.5, 2.5], np.float32))
  data = training_data.TrainingData.from_dataset(sphere).replace(keypoints=keypoints)
  state = train.init_state(model, config)
  step = jax.jit(train.train_step, static_argnums=(0, 1))
  new_state, statistics = step(model, config, state, data, np.float32(0.5))
  error = float(statistics["keypoint_depth"])
  assert error > 0  # an untrained field is a fog, not a surface at the keypoints
  mse = 10 ** (-float(statistics["psnr"]) / 10)
  assert float(statistics["loss"]) >= mse + 5.0 * error - 1e-6
  assert all(np.all(np.isfinite(leaf)) for leaf in jax.tree.leaves(new_state.variables))
  for off in (SMALL_CONFIG, dataclasses.replace(SMALL_CONFIG, keypoint_depth_weight=0.0)):
    _, without = step(model, off, state, data, np.float32(0.5))
    assert "keypoint_depth" not in without
