"""The catalogue of bad inputs (issue 68), dataset files: paths that leave the dataset folder,
and values a transforms.json can hold that used to end in a traceback or a silently wrong run
(a repeated frame, a singular applied_transform, an absurd lens or camera position, cameras that
do not move, degenerate bounds, masks that leave no pixel, a Blender scene without test images).
Each must be one clear error naming the file and the entry at fault, before any work is done."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from signerf_jax import camera, files
from signerf_jax.data import Dataset
from signerf_jax.errors import InputError
from signerf_jax.nerf.training_data import TrainingData
from test_bad_input_catalogue import inputs, copy, assert_one_clear_error  # noqa: F401


def edited_scene(tmp_path: Path, inputs, change) -> tuple[Path, Path]:
  """A copy of the catalogue's scene whose transforms.json `change(meta, scene)` edited in
  place; (the scene, its transforms.json)."""
  scene = copy(inputs["scene"], tmp_path / "scene")
  path = scene / "transforms.json"
  meta = json.loads(path.read_text())
  change(meta, scene)
  path.write_text(json.dumps(meta))
  return scene, path


def train_argv(tmp_path: Path, scene: Path, *extra: str) -> list[str]:
  return ["train", "--data", str(scene), "--run", str(tmp_path / "r"), "--steps", "1", *extra]


def relative_path_out_of_the_folder(tmp_path, inputs):
  (tmp_path / "outside").mkdir()
  files.write_image(tmp_path / "outside" / "secret.png", np.zeros((16, 16, 3)))

  def change(meta, scene):
    meta["frames"][3]["file_path"] = "../outside/secret.png"

  scene, path = edited_scene(tmp_path, inputs, change)
  return (train_argv(tmp_path, scene),
          [str(path), "frames[3].file_path", "points outside the folder"],
          tmp_path / "r")


def absolute_mask_path_out_of_the_folder(tmp_path, inputs):
  secret = tmp_path / "secret.png"
  files.write_image(secret, np.ones((16, 16)))

  def change(meta, scene):
    meta["frames"][1]["mask_path"] = str(secret)

  scene, path = edited_scene(tmp_path, inputs, change)
  return (train_argv(tmp_path, scene),
          [str(path), "frames[1].mask_path", "points outside the folder"],
          tmp_path / "r")


def image_symlinked_out_of_the_folder(tmp_path, inputs):
  scene = copy(inputs["scene"], tmp_path / "scene")
  outside = tmp_path / "elsewhere.png"
  image = scene / "images" / "frame_00002.png"
  image.rename(outside)
  image.symlink_to(outside)  # The name is inside; the file it reads is not.
  return (train_argv(tmp_path, scene),
          [str(scene / "transforms.json"), "frames[2].file_path",
           "points outside the folder", str(outside)], tmp_path / "r")


def repeated_frame(tmp_path, inputs):
  def change(meta, scene):
    meta["frames"][3]["file_path"] = "./" + meta["frames"][1]["file_path"]

  scene, path = edited_scene(tmp_path, inputs, change)
  return (train_argv(tmp_path, scene),
          [str(path), "frames[3].file_path", "same image as frames[1].file_path"],
          tmp_path / "r")


def singular_applied_transform(tmp_path, inputs):
  def change(meta, scene):
    meta["applied_transform"] = [[1, 0, 0, 0], [0, 0, 0, 0], [0, 0, 1, 0]]

  scene, path = edited_scene(tmp_path, inputs, change)
  return (train_argv(tmp_path, scene), [str(path), "applied_transform", "singular"],
          tmp_path / "r")


def absurd_distortion_coefficient(tmp_path, inputs):
  def change(meta, scene):
    meta["camera_model"], meta["k1"] = "OPENCV", 1e30

  scene, path = edited_scene(tmp_path, inputs, change)
  return (train_argv(tmp_path, scene), [str(path), "k1", "1e+30 is no real lens's"],
          tmp_path / "r")


def camera_a_googol_away(tmp_path, inputs):
  def change(meta, scene):
    meta["frames"][2]["transform_matrix"][0][3] = 1e300

  scene, path = edited_scene(tmp_path, inputs, change)
  return (train_argv(tmp_path, scene),
          [str(path), "frames[2].transform_matrix", "camera position"], tmp_path / "r")


def cameras_that_do_not_move(tmp_path, inputs):
  def change(meta, scene):
    del meta["signerf"]  # A plain capture: its frame is found from the cameras.
    for frame in meta["frames"]:
      frame["transform_matrix"] = meta["frames"][0]["transform_matrix"]

  scene, _ = edited_scene(tmp_path, inputs, change)
  return (train_argv(tmp_path, scene),
          [str(scene), "cameras do not move", "--scene_center", "--scene_radius"],
          tmp_path / "r")


def degenerate_scene_bounds(tmp_path, inputs):
  def change(meta, scene):
    meta["signerf"]["scene_bounds"] = [[0, 0, 0], [1e-300, 1e-300, 1e-300]]

  scene, path = edited_scene(tmp_path, inputs, change)
  return (train_argv(tmp_path, scene), [str(path), "signerf.scene_bounds", "degenerate"],
          tmp_path / "r")


def masks_that_ignore_every_pixel(tmp_path, inputs):
  def change(meta, scene):
    for index, frame in enumerate(meta["frames"]):
      files.write_image(scene / "masks" / f"{index}.png", np.zeros((16, 16)))
      frame["mask_path"] = f"masks/{index}.png"

  scene, _ = edited_scene(tmp_path, inputs, change)
  return (train_argv(tmp_path, scene),
          [str(scene / "masks"), "mask_path", "no pixel is left to train"], tmp_path / "r")


def blender_scene_without_test_images(tmp_path, inputs):
  scene = tmp_path / "blender"
  for split, count in (("train", 3), ("test", 2)):
    frames = []
    for index in range(count):
      angle = 2 * np.pi * index / count + (0.3 if split == "test" else 0.0)
      eye = np.array([4 * np.cos(angle), 4 * np.sin(angle), 1.0], np.float32)
      pose = np.asarray(camera.look_at(eye, np.zeros(3, np.float32)))
      frames.append({"file_path": f"./{split}/r_{index}", "transform_matrix": pose.tolist()})
      if split == "train":  # Every test image is missing.
        files.write_image(scene / split / f"r_{index}.png", np.full((8, 8, 4), 0.5))
    files.write_json(scene / f"transforms_{split}.json", {"camera_angle_x": 0.69, "frames": frames})
  # Refused before the training, which would only find no held-out view at its end.
  return (train_argv(tmp_path, scene),
          [str(scene / "transforms_test.json"), "the test split's images are all missing"],
          tmp_path / "r")


CASES = [
    relative_path_out_of_the_folder, absolute_mask_path_out_of_the_folder,
    image_symlinked_out_of_the_folder, repeated_frame, singular_applied_transform,
    absurd_distortion_coefficient, camera_a_googol_away, cameras_that_do_not_move,
    degenerate_scene_bounds, masks_that_ignore_every_pixel, blender_scene_without_test_images,
]


@pytest.mark.parametrize("case", CASES, ids=lambda case: case.__name__)
def test_a_bad_dataset_is_one_clear_error(tmp_path, inputs, capsys, case):  # noqa: F811
  assert_one_clear_error(*case(tmp_path, inputs), capsys)



def test_training_data_whose_every_pixel_is_masked_out_is_refused():
  # What the loader's mask check guards, for datasets built in memory.
  eyes = np.array([[3.0, 0.0, 1.0], [0.0, 3.0, 1.0]], np.float32)
  cameras = camera.Cameras.create(np.asarray(camera.look_at(eyes, np.zeros(3, np.float32))),
                                  fx=8.0, width=4, height=4)
  dataset = Dataset(images=np.zeros((2, 4, 4, 3), np.float32), cameras=cameras,
                    image_names=("a.png", "b.png"),
                    scene_bounds=np.array([[-1, -1, -1], [1, 1, 1]], np.float32),
                    scene_kind="bounded", near=1.0, far=5.0, root="/data/scene",
                    masks=np.zeros((2, 4, 4), np.float32))
  with pytest.raises(InputError, match="the masks leave nothing to train on") as error:
    TrainingData.from_dataset(dataset)
  assert (error.value.path, error.value.field) == ("/data/scene", "masks")
  unmasked = dataclasses.replace(dataset, masks=None)
  assert TrainingData.from_dataset(unmasked).pixel_weights.shape == (2, 4, 4)
  # A caller's zero pixel weights are a choice (a fine-tune that leaves the field as it is).
  assert not np.any(TrainingData.from_dataset(unmasked, np.zeros((2, 4, 4))).pixel_weights)
