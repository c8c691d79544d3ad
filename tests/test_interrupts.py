"""Ctrl-C (SIGINT) and SIGTERM during `signerf train`, in a real process on a tiny scene: the
steps since the last checkpoint are saved, one line names the step and the run, the exit code is
130 / 143, no traceback, and the same command resumes from that checkpoint."""

from __future__ import annotations

import re
import signal
import subprocess
from pathlib import Path

import pytest

from signerf_jax import checkpoints

from streamed_process import EXIT_TIMEOUT, SIGNERF, StreamedProcess

pytestmark = pytest.mark.slow

INTERRUPTED = re.compile(r"^signerf train: interrupted at step (\d+); checkpoint saved in (.+); "
                         r"run the same command to resume$", re.MULTILINE)


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
  """A 5-view 16 px synthetic scene with nothing but the ground: written in seconds."""
  path = tmp_path_factory.mktemp("interrupts") / "scene"
  subprocess.run(SIGNERF + ["synthesize", "--out", str(path),
                            "--gin_param", "synthetic_cameras.num_views = 5",
                            "--gin_param", "synthetic_cameras.image_size = 16",
                            "--gin_param", "synthetic_scene.num_meshes = 0"],
                 check=True, capture_output=True, timeout=EXIT_TIMEOUT)
  return path


def training(scene: Path, run_dir: Path) -> StreamedProcess:
  """`signerf train` in a process of its own. Far more steps than run: only a signal ends it.
  No checkpoint falls due (every 1000 steps, and not by time): whatever a run finds when
  resumed, the interrupt wrote."""
  return StreamedProcess(["train", "--data", str(scene), "--run", str(run_dir), "--steps",
                          "100000", "--skip_eval", "--gin_param",
                          "TrainConfig.checkpoint_every_seconds = 1e6"])


def _checkpoint_step(run_dir: Path) -> int:
  _, metadata = checkpoints.read(run_dir)
  return int(metadata["step"])


def stopped_at(process: StreamedProcess, signum: int, exit_code: int, run_dir: Path) -> int:
  """Sends `signum` to the training; checks it exits with `exit_code`, no traceback, and one line
  naming the step and `run_dir`, whose checkpoint holds that step. Returns the step."""
  code, stderr = process.stop(lambda: process.process.send_signal(signum))
  assert code == exit_code, stderr
  assert "Traceback" not in stderr
  reported = INTERRUPTED.search(stderr)
  assert reported, stderr
  step = int(reported.group(1))
  assert Path(reported.group(2)) == run_dir
  assert _checkpoint_step(run_dir) == step
  return step


def test_sigint_then_sigterm_checkpoint_the_step_reached_and_the_same_command_resumes(
    scene, tmp_path):
  run_dir = tmp_path / "run"
  # Ctrl-C a few steps in: before it, no checkpoint was due.
  first = training(scene, run_dir)
  shown = first.wait_for_step(3)
  assert not checkpoints.has_checkpoint(run_dir)
  step = stopped_at(first, signal.SIGINT, 130, run_dir)
  assert step >= shown

  # The same command resumes from that step; SIGTERM stops it as Ctrl-C did.
  second = training(scene, run_dir)
  shown = second.wait_for_step(step + 2)
  assert second.steps_shown()[0] >= step  # Counting on from the checkpoint, not from 0.
  resumed_step = stopped_at(second, signal.SIGTERM, 143, run_dir)
  assert resumed_step >= shown > step
