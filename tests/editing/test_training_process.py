"""An edit's NeRF trainings in a process of their own (`editing.commands.training_process`): only
the stages that train run there, they train the same NeRFs bit for bit, what stops the child is
raised in the parent, and Ctrl-C or SIGTERM checkpoints the child's steps and stops the command
with one line and no traceback."""

from __future__ import annotations

import os
import re
import signal
import subprocess
from pathlib import Path

import gin
import jax
import numpy as np
import pytest

from signerf_jax import allocator, checkpoints, configs
from signerf_jax.editing import commands, stages
from signerf_jax.editing.commands import training_process
from signerf_jax.editing.project import EditDirectory
from signerf_jax.errors import InputError

from streamed_process import StreamedProcess

pytestmark = pytest.mark.slow

INTERRUPTED = re.compile(r"^signerf edit: interrupted at step (\d+); checkpoint saved in (.+); "
                         r"run the same command to resume$", re.MULTILINE)


def edit_bindings(scene_dir: Path, model: Path, **overrides: str) -> list[str]:
  """A box edit of the tiny scene with a few NeRF steps and a 2-step sampler."""
  values = {"EditConfig.data": repr(str(scene_dir)), "EditConfig.prompt": "'a red cow'",
            "EditConfig.model": repr(str(model)), "EditConfig.nerf_update": "'finetune'",
            "SelectionConfig.kind": "'box'",
            "SelectionConfig.box_min": "(-0.3, -0.3, -0.1)",
            "SelectionConfig.box_max": "(0.3, 0.3, 0.3)",
            "SheetConfig.tile_size": "16", "original/TrainConfig.steps": "20",
            "finetune/TrainConfig.steps": "5", "PreviewConfig.seeds": "(0,)",
            "first_iteration/GenerationOptions.num_inference_steps": "2",
            "UpdateConfig.views_per_device": "4"}
  values.update(overrides)
  return [f"{name} = {value}" for name, value in values.items()]


def settings_of(chosen: list[str]):
  configs.parse_gin([], chosen)
  try:
    return commands.edit_settings()
  finally:
    gin.clear_config()


@pytest.fixture
def child_keeps_freed_memory(monkeypatch):
  """The environment of a `signerf` outside the tests: the child keeps freed memory."""
  monkeypatch.setenv(allocator.ENVIRONMENT_VARIABLE, "1")


def test_the_runner_is_chosen_where_only_a_child_would_keep_freed_memory(monkeypatch):
  monkeypatch.setattr(allocator, "_kept", False)
  monkeypatch.setenv(allocator.ENVIRONMENT_VARIABLE, "1")
  expected = (training_process.run_in_training_process if allocator._glibc() is not None  # pylint: disable=protected-access
              else None)
  assert training_process.training_runner() is expected
  monkeypatch.setattr(allocator, "_kept", True)  # This process keeps it already.
  assert training_process.training_runner() is None
  monkeypatch.setattr(allocator, "_kept", False)
  monkeypatch.setenv(allocator.ENVIRONMENT_VARIABLE, "0")
  assert training_process.training_runner() is None
  monkeypatch.setenv(allocator.ENVIRONMENT_VARIABLE, "1")
  monkeypatch.setenv("JAX_PLATFORMS", "cuda")
  assert training_process.training_runner() is None


def test_only_the_trainings_run_in_the_child_and_they_train_the_same_nerfs(
    tiny_scene, random_model, tmp_path, child_keeps_freed_memory):
  scene_dir, _ = tiny_scene
  settings = settings_of(edit_bindings(scene_dir, random_model))
  in_child = []

  def run_training(stage, context):
    in_child.append(stage.name)
    return training_process.run_in_training_process(stage, context)

  lines = []
  stages.run_edit(tmp_path / "child", settings, until="finetune", progress=False,
                  log=lines.append, run_training=run_training)
  stages.run_edit(tmp_path / "here", settings, until="finetune", progress=False,
                  log=lambda line: None)
  assert in_child == ["original", "finetune"]
  assert any(re.search(r"\] original: 20 steps .* on \d+ views", line) for line in lines), lines
  for run in ("original", "edited"):
    child, child_metadata = checkpoints.read(tmp_path / "child" / run)
    here, here_metadata = checkpoints.read(tmp_path / "here" / run)
    assert child_metadata["step"] == here_metadata["step"] > 0
    for a, b in zip(jax.tree.leaves(child), jax.tree.leaves(here)):
      assert np.array_equal(np.asarray(a), np.asarray(b)), run


def test_bad_input_found_in_the_child_is_raised_in_the_parent_naming_the_field(
    tiny_scene, random_model, tmp_path, child_keeps_freed_memory):
  scene_dir, _ = tiny_scene
  (tmp_path / "earlier").mkdir()
  settings = settings_of(edit_bindings(
      scene_dir, random_model, **{"EditConfig.replay": repr(str(tmp_path / "earlier"))}))
  with pytest.raises(InputError, match="schedule") as error:
    stages.run_edit(tmp_path / "edit", settings, until="original", progress=False,
                    log=lambda line: None,
                    run_training=training_process.run_in_training_process)
  assert error.value.field == "EditConfig.replay"


def edit_process(scene_dir: Path, model: Path, edit_dir: Path) -> StreamedProcess:
  """`signerf edit` in a process of its own whose child keeps freed memory; the original NeRF
  trains far more steps than run, so only a signal ends it."""
  gin_params = edit_bindings(scene_dir, model, **{
      "original/TrainConfig.steps": "100000",
      "original/TrainConfig.checkpoint_every_seconds": "1e6"})
  return StreamedProcess(["edit", "--edit", str(edit_dir)]
                         + [argument for binding in gin_params
                            for argument in ("--gin_param", binding)],
                         {allocator.ENVIRONMENT_VARIABLE: "1"})


@pytest.mark.parametrize("signum, to_group, exit_code", [
    (signal.SIGINT, True, 130),  # Ctrl-C: the terminal signals the parent and the child.
    (signal.SIGTERM, False, 143),  # `kill`: the parent alone, which passes it on.
    (signal.SIGINT, False, 130),
], ids=["ctrl_c", "sigterm_to_the_parent", "sigint_to_the_parent"])
def test_a_signal_checkpoints_the_childs_training_and_stops_the_edit_in_one_line(
    tiny_scene, random_model, tmp_path, signum, to_group, exit_code):
  scene_dir, _ = tiny_scene
  edit = edit_process(scene_dir, random_model, tmp_path / "edit")
  shown = edit.wait_for_step(3)
  pid = edit.process.pid
  code, stderr = edit.stop(lambda: os.killpg(pid, signum) if to_group else os.kill(pid, signum))
  assert code == exit_code, stderr
  assert "Traceback" not in stderr
  reported = INTERRUPTED.search(stderr)
  assert reported, stderr
  step = int(reported.group(1))
  assert step >= shown
  assert Path(reported.group(2)) == tmp_path / "edit" / "original"
  _, metadata = checkpoints.read(tmp_path / "edit" / "original")
  assert metadata["step"] == step
  assert EditDirectory(tmp_path / "edit").record("original") is None


def test_a_child_killed_without_a_word_stops_the_edit_naming_the_signal(tiny_scene, random_model,
                                                                       tmp_path):
  scene_dir, _ = tiny_scene
  edit = edit_process(scene_dir, random_model, tmp_path / "edit")
  edit.wait_for_step(3)
  children = subprocess.run(["pgrep", "-P", str(edit.process.pid), "-f", "spawn_main"],
                            capture_output=True, text=True, check=True).stdout.split()
  assert len(children) == 1, children
  code, stderr = edit.stop(lambda: os.kill(int(children[0]), signal.SIGKILL))
  assert code == 1, stderr
  assert ("the original stage's training process was killed by SIGKILL before it finished; run "
          "the same command to resume") in stderr
  assert EditDirectory(tmp_path / "edit").record("original") is None
