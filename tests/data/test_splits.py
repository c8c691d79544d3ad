"""Held-out views: the source's own split, eval_every, explicit lists; never trained on."""

import dataclasses

import numpy as np
import pytest

from signerf_jax import files
from signerf_jax.data import load_dataset, splits, write_nerfstudio
from signerf_jax.errors import InputError
from signerf_jax.nerf import train, training_run

NAMES = tuple(f"images/frame_{index:05d}.png" for index in range(10))


def test_every_nth_view_is_held_out_by_default():
  np.testing.assert_array_equal(splits.select_views(NAMES, "eval"), [0, 8])
  np.testing.assert_array_equal(splits.select_views(NAMES, "eval", eval_every=3), [0, 3, 6, 9])
  np.testing.assert_array_equal(splits.select_views(NAMES, "train", eval_every=3),
                                [1, 2, 4, 5, 7, 8])


@pytest.mark.parametrize("held_out", [("images/frame_00004.png", "frame_00007"),
                                      ("./images/frame_00004", "frame_00007.jpg")])
def test_explicit_held_out_names_win_and_match_without_extension(held_out):
  source = {"train": range(5), "eval": range(5, 10)}
  evaluation = splits.select_views(NAMES, "eval", held_out=held_out, source_splits=source,
                                   eval_every=2)
  np.testing.assert_array_equal(evaluation, [4, 7])
  training = splits.select_views(NAMES, "train", held_out=held_out)
  assert set(training).isdisjoint(evaluation) and len(training) == 8


def test_unknown_or_ambiguous_held_out_names_are_errors_naming_them():
  with pytest.raises(InputError, match="no view is named frame_00042") as error:
    splits.select_views(NAMES, "eval", held_out=["frame_00042"])
  assert error.value.field == "held_out"
  with pytest.raises(InputError, match="several views end in a"):
    splits.select_views(("x/a.png", "y/a.png"), "eval", held_out=["a"])


def test_source_split_is_used_unless_eval_every_is_given():
  source = {"train": (1, 2, 3), "eval": (5,)}
  np.testing.assert_array_equal(splits.select_views(NAMES, "train", source_splits=source),
                                [1, 2, 3])
  np.testing.assert_array_equal(splits.select_views(NAMES, "eval", source_splits=source), [5])
  np.testing.assert_array_equal(
      splits.select_views(NAMES, "eval", source_splits=source, eval_every=5), [0, 5])
  with pytest.raises(InputError, match="both training and evaluation"):
    splits.select_views(NAMES, "train", source_splits={"train": (1, 2), "eval": (2,)})


@pytest.mark.parametrize("keys, expected_eval", [
    ({"train_filenames": [1, 2, 3, 5, 6], "val_filenames": [0, 4]}, [0, 4]),
    ({"train_filenames": [1, 2, 3, 5, 6], "test_filenames": [7]}, [7]),
    # nerfstudio evaluates on val when both are given; test views are then in neither split.
    ({"train_filenames": [1, 2, 3], "val_filenames": [0], "test_filenames": [7]}, [0])])
def test_nerfstudio_split_keys_are_honoured(tmp_path, dataset_factory, keys, expected_eval):
  dataset = dataset_factory(count=8, with_extras=False)
  path = write_nerfstudio(tmp_path, dataset)
  meta = files.read_json(path)
  names = [frame["file_path"] for frame in meta["frames"]]
  meta.update({key: [names[index] for index in indices] for key, indices in keys.items()})
  files.write_json(path, meta)
  training = load_dataset(tmp_path, split="train")
  evaluation = load_dataset(tmp_path, split="eval")
  assert training.image_names == tuple(names[index] for index in keys["train_filenames"])
  assert evaluation.image_names == tuple(names[index] for index in expected_eval)
  # eval_every overrides the file's split.
  assert load_dataset(tmp_path, split="eval", eval_every=4).image_names == (names[0], names[4])


def test_split_keys_naming_unknown_files_are_errors(tmp_path, dataset_factory):
  path = write_nerfstudio(tmp_path, dataset_factory(count=4, with_extras=False))
  meta = files.read_json(path)
  meta["train_filenames"] = ["images/frame_00001.png", "images/nope.png"]
  files.write_json(path, meta)
  with pytest.raises(InputError, match="nope.png") as error:
    load_dataset(tmp_path)
  assert error.value.field == "train_filenames" and error.value.path == str(path)


def write_split_files(root, dataset, test_indices, repeat_test_as_val=True):
  """An instant-NGP-style capture: transforms_{train,test,val}.json with pixel intrinsics and
  file paths without extension (as ../shared/data/stitch)."""
  write_nerfstudio(root, dataset)
  meta = files.read_json(root / "transforms.json")
  (root / "transforms.json").unlink()
  for frame in meta["frames"]:
    frame["file_path"] = "./" + frame["file_path"][:-len(".png")]
  del meta["signerf"], meta["applied_transform"]
  test = [frame for index, frame in enumerate(meta["frames"]) if index in test_indices]
  train = [frame for index, frame in enumerate(meta["frames"]) if index not in test_indices]
  files.write_json(root / "transforms_train.json", {**meta, "frames": train})
  files.write_json(root / "transforms_test.json", {**meta, "frames": test})
  if repeat_test_as_val:
    files.write_json(root / "transforms_val.json", {**meta, "frames": test})


def test_split_files_with_intrinsics_are_a_real_capture_not_a_blender_scene(tmp_path,
                                                                            dataset_factory):
  dataset = dataset_factory(count=9, with_extras=False, distortion=(-0.01, 0.02, 0.001, 0.0))
  write_split_files(tmp_path, dataset, test_indices=(2, 5))
  training = load_dataset(tmp_path, split="train")
  evaluation = load_dataset(tmp_path, split="eval")
  everything = load_dataset(tmp_path, split="all")
  assert evaluation.image_names == ("./images/frame_00002", "./images/frame_00005")
  assert training.num_images == 7 and everything.num_images == 9  # val repeats test: once
  assert training.scene_kind == "unbounded" and training.background_color is None
  np.testing.assert_allclose(training.cameras.distortion[0, :4], [-0.01, 0.02, 0.001, 0.0],
                             rtol=1e-6)
  np.testing.assert_allclose(evaluation.images[1], dataset.images[5], atol=0.5 / 255 + 1e-6)
  np.testing.assert_array_equal(training.world_from_source, evaluation.world_from_source)


def test_held_out_images_are_never_read_for_training(tmp_path, dataset_factory):
  """The held-out views' files are deleted: loading and training the train split must not need
  them (they would be an error if read), and evaluating needs exactly them."""
  dataset = dataset_factory(count=6, width=8, height=6, with_extras=False)
  write_split_files(tmp_path, dataset, test_indices=(1, 4))
  for index in (1, 4):
    (tmp_path / "images" / f"frame_{index:05d}.png").unlink()
  training = load_dataset(tmp_path, split="train")
  assert not {"./images/frame_00001", "./images/frame_00004"} & set(training.image_names)
  trainer = training_run.make_trainer(training, config=dataclasses.replace(train.TrainConfig(),
                                                                     steps=1))
  assert trainer.data.images.shape[0] == 4
  with pytest.raises(InputError, match="not found") as error:
    load_dataset(tmp_path, split="eval")
  assert "frame_00001" in error.value.path
