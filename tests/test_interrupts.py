"""Ctrl-C (SIGINT) and SIGTERM during `signerf train`, in a real process on a tiny scene: the
steps since the last checkpoint are saved, one line names the step and the run, the exit code is
130 / 143, no traceback, and the same command resumes from that checkpoint."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from signerf_jax import checkpoints

pytestmark = pytest.mark.slow

SIGNERF = [sys.executable, "-m", "signerf_jax.cli"]
# The first step compiles (tens of seconds on two busy cores); the others take well under one.
PROGRESS_TIMEOUT = 300.0
EXIT_TIMEOUT = 120.0
# tqdm's bar: "  0%|          | 9/100000 [00:29<28:28:16,  1.03s/step]".
PROGRESS = re.compile(r"(\d+)/100000 \[")
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


class Training:
  """`signerf train` in a process of its own, its stderr read as it comes."""

  def __init__(self, scene: Path, run_dir: Path):
    # Far more steps than run: only a signal ends it. No checkpoint falls due (every 1000
    # steps, and not by time): whatever a run finds when resumed, the interrupt wrote.
    self.process = subprocess.Popen(
        SIGNERF + ["train", "--data", str(scene), "--run", str(run_dir), "--steps", "100000",
                   "--skip_eval", "--gin_param", "TrainConfig.checkpoint_every_seconds = 1e6"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    self.stderr = ""
    self._reader = threading.Thread(target=self._read, daemon=True)
    self._reader.start()

  def _read(self) -> None:
    while chunk := self.process.stderr.read1(4096):
      self.stderr += chunk.decode(errors="replace")

  def steps_shown(self) -> list[int]:
    return [int(count) for count in PROGRESS.findall(self.stderr)]

  def wait_for_step(self, step: int) -> int:
    """Waits until the progress bar shows `step` steps or more; returns the count shown."""
    deadline = time.monotonic() + PROGRESS_TIMEOUT
    while time.monotonic() < deadline:
      shown = self.steps_shown()
      if shown and shown[-1] >= step:
        return shown[-1]
      assert self.process.poll() is None, f"signerf train ended early:\n{self.stderr}"
      time.sleep(0.1)
    self.process.kill()
    pytest.fail(f"no progress past step {step} in {PROGRESS_TIMEOUT:.0f} s:\n{self.stderr}")

  def stop(self, signum: int) -> tuple[int, str]:
    """Sends `signum`; returns the exit code and the whole stderr."""
    self.process.send_signal(signum)
    try:
      code = self.process.wait(timeout=EXIT_TIMEOUT)
    except subprocess.TimeoutExpired:
      self.process.kill()
      self.process.wait()
      pytest.fail(f"signerf train did not stop within {EXIT_TIMEOUT:.0f} s:\n{self.stderr}")
    self._reader.join(timeout=10)
    return code, self.stderr


def _checkpoint_step(run_dir: Path) -> int:
  _, metadata = checkpoints.read(run_dir)
  return int(metadata["step"])


def stopped_at(training: "Training", signum: int, exit_code: int, run_dir: Path) -> int:
  """Sends `signum` to the training; checks it exits with `exit_code`, no traceback, and one line
  naming the step and `run_dir`, whose checkpoint holds that step. Returns the step."""
  code, stderr = training.stop(signum)
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
  first = Training(scene, run_dir)
  shown = first.wait_for_step(3)
  assert not checkpoints.has_checkpoint(run_dir)
  step = stopped_at(first, signal.SIGINT, 130, run_dir)
  assert step >= shown

  # The same command resumes from that step; SIGTERM stops it as Ctrl-C did.
  second = Training(scene, run_dir)
  shown = second.wait_for_step(step + 2)
  assert second.steps_shown()[0] >= step  # Counting on from the checkpoint, not from 0.
  resumed_step = stopped_at(second, signal.SIGTERM, 143, run_dir)
  assert resumed_step >= shown > step
