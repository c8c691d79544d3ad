"""A time-budgeted run records the progress its schedule had at each step, and a run given that
record back repeats it bit for bit (`training_run.replay_progress`, `signerf train --replay`)."""

import dataclasses

import jax
import numpy as np
import pytest
from small_nerf import SMALL_CONFIG, small_model

from signerf_jax import checkpoints, cli, ownership
from signerf_jax.data import synthetic_render
from signerf_jax.nerf import training_run


def assert_bitwise_equal(first, second):
  first, second = jax.tree.leaves(first), jax.tree.leaves(second)
  assert len(first) == len(second)
  for a, b in zip(first, second):
    assert np.array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.slow  # two compilations of the training step
def test_a_time_budgeted_run_replayed_has_the_same_parameters_bit_for_bit(sphere, tmp_path):
  model = small_model(sphere)
  config = dataclasses.replace(SMALL_CONFIG, steps=1_000_000, max_seconds=2.0)
  timed = training_run.make_trainer(sphere, model=model, config=config)
  timed.run(until_step=1, progress=False)
  # The budget's seconds start after the compilation, so that a busy machine still fits steps.
  timed.seconds_trained = 0.0
  timed.run(progress=False)
  progress = np.asarray(timed.progress_record, np.float32)
  assert len(progress) == timed.step > 2
  assert np.all(np.diff(progress) > 0) and progress[-1] <= 1.0
  # The schedule followed the seconds, not the steps (1e6 of them).
  assert progress[-1] > 0.5
  replayed = training_run.train(sphere, tmp_path, model=model, config=config,
                                replay_progress=progress, progress=False)
  assert replayed.step == timed.step
  assert_bitwise_equal(timed.state, replayed.state)
  np.testing.assert_array_equal(training_run.read_schedule(tmp_path), progress)


def test_a_resumed_run_keeps_its_schedule_up_to_its_checkpoint(sphere, tmp_path):
  model = small_model(sphere)
  config = dataclasses.replace(SMALL_CONFIG, steps=6)
  training_run.train(sphere, tmp_path, model=model, config=config, progress=False)
  recorded = training_run.read_schedule(tmp_path)
  np.testing.assert_allclose(recorded, np.arange(6) / 6, rtol=1e-6)
  with ownership.claimed(tmp_path, ownership.RUN):
    # Killed between the two writes: the schedule holds steps the checkpoint does not.
    training_run.write_schedule(tmp_path, [*recorded.tolist(), 0.99, 0.995])
    trainer = training_run.make_trainer(sphere, model=model, config=config)
    trainer.restore(tmp_path)
    assert trainer.progress_record == recorded.tolist()
    # A checkpoint without its schedule (written before schedules were): nothing to replay.
    (tmp_path / training_run.SCHEDULE_FILE).unlink()
    trainer.restore(tmp_path)
    assert trainer.progress_record is None


@pytest.mark.parametrize("record", [{"steps": 2, "progress": [0.1]},
                                    {"steps": 1, "progress": [1.5]}, {"progress": "x"}])
def test_a_malformed_schedule_is_a_clear_error(tmp_path, record):
  from signerf_jax import files
  from signerf_jax.errors import InputError

  files.write_json(tmp_path / training_run.SCHEDULE_FILE, record)
  with pytest.raises(InputError, match="schedule.json"):
    training_run.read_schedule(tmp_path)


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
  directory = tmp_path_factory.mktemp("scene")
  with ownership.claimed(directory, ownership.DATASET):
    synthetic_render.generate(directory, seed=0, rig=synthetic_render.CameraRig(
        num_views=12, image_size=32))
  return directory


@pytest.mark.slow
def test_signerf_train_replays_a_20_second_run_bit_for_bit(small_scene, tmp_path, capsys):
  assert cli.main(["train", "--data", str(small_scene), "--run", str(tmp_path / "timed"),
                   "--max_seconds", "20", "--skip_eval"]) == 0
  assert cli.main(["train", "--replay", str(tmp_path / "timed"), "--run",
                   str(tmp_path / "replayed"), "--skip_eval"]) == 0
  timed, timed_metadata = checkpoints.read(tmp_path / "timed")
  replayed, replayed_metadata = checkpoints.read(tmp_path / "replayed")
  assert replayed_metadata["step"] == timed_metadata["step"]
  assert_bitwise_equal(timed, replayed)


def test_a_replay_takes_nothing_but_the_run(small_scene, tmp_path, capsys):
  (tmp_path / "a").mkdir()
  code = cli.main(["train", "--replay", str(tmp_path / "a"), "--run", str(tmp_path / "b"),
                   "--data", str(small_scene)])
  assert code == 2 and "leave out --data" in capsys.readouterr().err
  (tmp_path / "empty").mkdir()
  code = cli.main(["train", "--replay", str(tmp_path / "empty"), "--run", str(tmp_path / "b")])
  assert code == 2 and "has no schedule.json" in capsys.readouterr().err
