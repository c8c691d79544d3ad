"""Every command that writes leaves the user's files as they were (issue 68): files in and around
each output directory and the input dataset — dot-files, names like the project's temporary
files and stage folders, a capture's frames — are byte-identical after synthesize, train,
eval, render, place, preview, edit, update, finetune and demo, run and re-run the way a user
does (resumed, redone, started over); outputs that overlap an input, or a folder of the user's
files, are refused; and two processes never write one run."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import gin
import numpy as np
import pytest

from signerf_jax import cli, files, ownership

pytestmark = pytest.mark.slow

# Files a user keeps beside the project's: dot-files, names like the project's temporary files
# (".<stem>.<8 characters>.<suffix>"), folders named like its stages, a frame named like its own.
USER_FILES = (".env.database", ".profile.original", "notes/deep/.vimrc.template",
              "notes/.htaccess.previous", "notes/.tool.settings.json",
              "selection/my_selection.json", "reference/paper.pdf", "eval/mine.png",
              ".checkpoint.a1b2c3d4.msgpack", ".sheet.0badc0de.png", "images/frame_00042.png",
              "update/images/notes.txt")
# The edit's budgets, as small as the pipeline runs with (the random model's tiles are 16 px).
TINY_EDIT = ("SheetConfig.tile_size = 16", "original/TrainConfig.steps = 20",
             "finetune/TrainConfig.steps = 4", "retrain/TrainConfig.steps = 4",
             "first_iteration/GenerationOptions.num_inference_steps = 2",
             "PreviewConfig.seeds = (0,)", "UpdateConfig.views_per_device = 4",
             "EvaluationConfig.independent_views = 2", "EvaluationConfig.video_frames = 0",
             "NerfConsistencySettings.enabled = False")
TINY_SCENE = ("synthetic_cameras.num_views = 6", "synthetic_cameras.image_size = 16",
              "synthetic_scene.num_meshes = 0")


class UserFiles:
  """The user's files written so far and their contents."""

  def __init__(self):
    self.contents: dict[Path, bytes] = {}

  def add(self, directory: Path, names=USER_FILES) -> None:
    for name in names:
      path = directory / name
      path.parent.mkdir(parents=True, exist_ok=True)
      path.write_bytes(f"the user's {path}".encode())
      self.contents[path] = path.read_bytes()

  def assert_unchanged(self, after: str) -> None:
    for path, data in self.contents.items():
      assert path.is_file() and path.read_bytes() == data, f"{path} changed by {after}"


def signerf(*argv: str, gin_params=()) -> int:
  """Runs `signerf ARGV --gin_param P ...` in this process; returns its exit code."""
  argv = list(argv) + [item for param in gin_params for item in ("--gin_param", param)]
  gin.clear_config()
  try:
    code = cli.main(argv)
  except SystemExit as exit_:
    code = exit_.code
  gin.clear_config()
  return code


def refused(capsys, *argv: str, gin_params=()) -> str:
  """The error line of a command that must be refused (exit 2, no traceback)."""
  capsys.readouterr()
  assert signerf(*argv, gin_params=gin_params) == 2
  error = capsys.readouterr().err
  assert "Traceback" not in error
  return error.strip().splitlines()[-1]


def write_capture(directory: Path) -> None:
  """A capture as nerfstudio names it: images/frame_00001.png ... frame_00010.png, transforms.json."""
  frames = []
  for index in range(1, 11):
    files.write_image(directory / "images" / f"frame_{index:05d}.png",
                      np.full((8, 8, 3), index / 10, np.float32))
    frames.append({"file_path": f"images/frame_{index:05d}.png",
                   "transform_matrix": np.eye(4).tolist()})
  (directory / "transforms.json").write_text(json.dumps({"fl_x": 8, "fl_y": 8, "cx": 4, "cy": 4,
                                                         "w": 8, "h": 8, "frames": frames}))


def test_every_command_leaves_the_users_files_as_they_were(tmp_path, random_model, capsys):
  user = UserFiles()
  user.add(tmp_path, (".env", "notes.txt", ".run.a1b2c3d4.json", "scene_notes/.keep"))
  capture = tmp_path / "capture"
  write_capture(capture)
  user.contents.update({path: path.read_bytes() for path in capture.rglob("*") if path.is_file()})

  # synthesize: never into a capture; into its own dataset again, with fewer views.
  assert "holds files signerf did not write" in refused(capsys, "synthesize", "--out",
                                                         str(capture))
  scene = tmp_path / "scene"
  assert signerf("synthesize", "--out", str(scene), gin_params=TINY_SCENE) == 0
  user.add(scene)
  assert signerf("synthesize", "--out", str(scene), "--seed", "1",
                 gin_params=TINY_SCENE[1:] + ("synthetic_cameras.num_views = 5",)) == 0
  assert not (scene / "images" / "frame_00005.png").exists()  # The sixth view's, recorded.
  user.assert_unchanged("synthesize")

  # train: never into its dataset; resumed, evaluated, rendered, started over.
  run = tmp_path / "run"
  for out, why in ((scene, "is the input given as --data"),
                   (scene / "run", "lies inside the input given as --data"),
                   (tmp_path, "holds the input given as --data")):
    assert why in refused(capsys, "train", "--data", str(scene), "--run", str(out))
  assert signerf("train", "--data", str(scene), "--run", str(run), "--steps", "3",
                 "--skip_eval") == 0
  user.add(run)
  assert signerf("train", "--data", str(scene), "--run", str(run), "--steps", "5") == 0
  assert signerf("eval", "--run", str(run)) == 0
  assert signerf("render", "--run", str(run)) == 0
  assert signerf("render", "--run", str(run), "--out", str(tmp_path / "renders")) == 0
  user.add(tmp_path / "renders")
  assert signerf("render", "--run", str(run), "--out", str(tmp_path / "renders"),
                 "--split", "train") == 0
  user.assert_unchanged("train, eval and render")
  other = tmp_path / "other_scene"
  assert signerf("synthesize", "--out", str(other), "--seed", "3", gin_params=TINY_SCENE) == 0
  assert "this run was trained on other data (the dataset was" in refused(
      capsys, "train", "--data", str(other), "--run", str(run), "--steps", "8")
  assert signerf("train", "--data", str(other), "--run", str(run), "--steps", "2",
                 "--start_over", "--skip_eval") == 0
  assert json.loads((run / "model.json").read_text())["fingerprint"]["root"] == str(
      other.resolve())
  assert not (run / "eval.json").exists()  # The earlier run's evaluation went with it.
  assert signerf("train", "--data", str(scene), "--run", str(run), "--steps", "3",
                 "--start_over", "--skip_eval") == 0
  user.assert_unchanged("a run started over")

  # The edit: placed, previewed, edited, redone with other settings, updated, fine-tuned.
  edit = tmp_path / "edit"
  assert "is the input given as --run" in refused(
      capsys, "place", "--run", str(run), "--edit", str(run), "--rectangle", "0", "3", "3", "13",
      "13", "--rectangle", "2", "3", "3", "13", "13")
  assert signerf("place", "--run", str(run), "--edit", str(edit), "--rectangle", "0", "3", "3",
                 "13", "13", "--rectangle", "2", "3", "3", "13", "13") == 0
  user.add(edit)
  model = ("--model", str(random_model), "--prompt", "a red cow")
  assert signerf("preview", "--edit", str(edit), *model, gin_params=TINY_EDIT) == 0
  assert signerf("edit", "--edit", str(edit), gin_params=TINY_EDIT) == 0
  user.add(edit / "dataset")
  assert signerf("edit", "--edit", str(edit), "--seed", "5", gin_params=TINY_EDIT) == 0
  assert signerf("update", "--edit", str(edit), "--redo", "reference", gin_params=TINY_EDIT) == 0
  assert signerf("finetune", "--edit", str(edit), gin_params=TINY_EDIT) == 0
  assert signerf("eval", "--edit", str(edit)) == 0
  user.assert_unchanged("the edit commands")
  assert (edit / "evaluation" / "metrics.json").is_file()

  # The demo, on a tiny scene with the random model; resumed with another prompt.
  demo = tmp_path / "demo"
  tiny_demo = TINY_EDIT + TINY_SCENE + ("synthetic_scene.num_primitives = 2",)
  assert signerf("demo", "--out", str(demo), "--model", str(random_model), "--quiet",
                 gin_params=tiny_demo) == 0
  for folder in (demo, demo / "scene", demo / "edit"):
    user.add(folder)
  assert signerf("demo", "--out", str(demo), "--model", str(random_model), "--quiet",
                 "--prompt", "a blue striped teapot", gin_params=tiny_demo) == 0
  user.assert_unchanged("the demo")


def test_two_trainings_into_one_run_give_one_clear_error_and_an_intact_run(tmp_path, capsys):
  scene = tmp_path / "scene"
  assert signerf("synthesize", "--out", str(scene), gin_params=TINY_SCENE) == 0
  run = tmp_path / "run"
  first = subprocess.Popen(
      [sys.executable, "-m", "signerf_jax.cli", "train", "--data", str(scene), "--run",
       str(run), "--steps", "400", "--skip_eval"], stdout=subprocess.PIPE,
      stderr=subprocess.PIPE, text=True)
  lock = run / ownership.MARKER_FOLDER / ownership.LOCK_FILE
  deadline = time.monotonic() + 240
  while not (lock.is_file() and lock.read_text().strip() == str(first.pid)):
    assert first.poll() is None and time.monotonic() < deadline, first.stderr.read()
    time.sleep(0.2)
  try:
    message = refused(capsys, "train", "--data", str(scene), "--run", str(run), "--steps", "2")
    assert f"in use by another signerf process (pid {first.pid})" in message
  finally:
    _, stderr = first.communicate(timeout=600)
  assert first.returncode == 0, stderr
  assert signerf("eval", "--run", str(run)) == 0  # The first run's checkpoint is whole.
  assert json.loads((run / "eval.json").read_text())["step"] == 400
