"""A `signerf` command in a process of its own, its stderr read as it comes: for the tests that
interrupt a training (`test_interrupts.py`, `editing/test_training_process.py`)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from typing import Callable

import pytest

SIGNERF = [sys.executable, "-m", "signerf_jax.cli"]
# The first step compiles (tens of seconds on two busy cores); the others take well under one.
PROGRESS_TIMEOUT = 300.0
EXIT_TIMEOUT = 120.0
# tqdm's bar of a 100000-step training: "  0%|          | 9/100000 [00:29<28:28:16,  1.03s/step]".
PROGRESS = re.compile(r"(\d+)/100000 \[")


class StreamedProcess:
  """`signerf ARGUMENTS` in a process group of its own (a signal can go to it alone or to the
  group, as Ctrl-C sends it), with `environment` added to this process's."""

  def __init__(self, arguments: list[str], environment: dict[str, str] | None = None):
    self.process = subprocess.Popen(
        SIGNERF + arguments, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        start_new_session=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1", **(environment or {})})
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
      assert self.process.poll() is None, f"the command ended early:\n{self.stderr}"
      time.sleep(0.1)
    self.kill()
    pytest.fail(f"no progress past step {step} in {PROGRESS_TIMEOUT:.0f} s:\n{self.stderr}")

  def stop(self, send: Callable[[], None]) -> tuple[int, str]:
    """Calls `send` (which signals the process); returns the exit code and the whole stderr."""
    send()
    try:
      code = self.process.wait(timeout=EXIT_TIMEOUT)
    except subprocess.TimeoutExpired:
      self.kill()
      pytest.fail(f"the command did not stop within {EXIT_TIMEOUT:.0f} s:\n{self.stderr}")
    self._reader.join(timeout=10)
    return code, self.stderr

  def kill(self) -> None:
    os.killpg(self.process.pid, signal.SIGKILL)
    self.process.wait()
