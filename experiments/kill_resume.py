"""kill -9 at random moments, then resume: the finished run must equal an uninterrupted one bit
for bit, and nothing may be lost or left half-written.

  python experiments/kill_resume.py [--kills 12] [--seed 0]

A small synthetic scene is trained by `signerf train` with a checkpoint after every step, so that
many kills land inside a checkpoint write. One run goes uninterrupted; the other is started,
SIGKILLed at a random moment (mostly a random number of checkpoint writes into training, plus a
random fraction of a step; sometimes during start-up), and started again (resuming) until it
finishes. After each kill
the run directory must hold a checkpoint that reads (the latest, or the previous one with a
warning) or none yet. At the end the two runs' parameters and optimiser states are compared
exactly, and the killed run's directory is searched for temporary files. Writes kill_resume.json
into --results DIR (default outputs/experiments/).
"""

from __future__ import annotations

import argparse
import os
import platform
import random
import signal
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import jax
import numpy as np

from signerf_jax import checkpoints, files

import machine  # experiments/machine.py (this script's directory is on sys.path)
import results_dir  # experiments/results_dir.py (this script's directory is on sys.path)

STEPS = 400
TRAIN_FLAGS = ["--steps", str(STEPS), "--skip_eval",
               "--gin_param", "TrainConfig.checkpoint_every_steps = 1",
               "--gin_param", "TrainConfig.checkpoint_every_seconds = 1000.0"]


def signerf(*arguments: str) -> list[str]:
  return [sys.executable, "-m", "signerf_jax.cli", *arguments]


def readable_step(run: Path) -> int | None:
  """The step of the checkpoint a resume would start from (None: no checkpoint yet)."""
  if not checkpoints.has_checkpoint(run):
    return None
  with warnings.catch_warnings():
    warnings.simplefilter("ignore")  # A fallback to the previous checkpoint is allowed.
    return int(checkpoints.read(run)[1]["step"])


def wait_for_saves(process: subprocess.Popen, checkpoint: Path, saves: int) -> bool:
  """Waits until `checkpoint` has been replaced `saves` times; False if the process ended."""
  def stamp():
    try:
      return checkpoint.stat().st_mtime_ns
    except FileNotFoundError:
      return None
  last, seen = stamp(), 0
  while seen < saves:
    if process.poll() is not None:
      return False
    time.sleep(0.01)
    current = stamp()
    if current != last and current is not None:
      seen, last = seen + 1, current
  return True


def leaves(run: Path) -> list[np.ndarray]:
  return [np.asarray(leaf) for leaf in jax.tree.leaves(checkpoints.read(run)[0])]


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--kills", type=int, default=12)
  parser.add_argument("--seed", type=int, default=0)
  results_dir.add_argument(parser)
  args = parser.parse_args()
  rng = random.Random(args.seed)
  load_at_start = os.getloadavg()
  work = Path(tempfile.mkdtemp(prefix="kill_resume_"))
  scene = work / "scene"
  subprocess.run(signerf("synthesize", "--out", str(scene), "--gin_param",
                         "synthetic_cameras.num_views = 8", "--gin_param",
                         "synthetic_cameras.image_size = 24"), check=True,
                 capture_output=True)
  start = time.perf_counter()
  subprocess.run(signerf("train", "--data", str(scene), "--run", str(work / "reference"),
                         *TRAIN_FLAGS), check=True, capture_output=True)
  uninterrupted_seconds = time.perf_counter() - start

  killed = work / "killed"
  kills = []
  while True:
    process = subprocess.Popen(signerf("train", "--data", str(scene), "--run", str(killed),
                                       *TRAIN_FLAGS), stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL)
    if len(kills) < args.kills:
      # Mostly during training, a random number of checkpoint writes in (so often inside one);
      # sometimes while the process is still starting.
      during_start = rng.random() < 0.2
      saves = 0 if during_start else rng.randint(1, 40)
      if wait_for_saves(process, killed / checkpoints.CHECKPOINT_NAME, saves):
        time.sleep(rng.uniform(0.5, 8.0) if during_start else rng.uniform(0.0, 0.3))
      if process.poll() is None:
        process.send_signal(signal.SIGKILL)
        process.wait()
        kills.append({"during": "start-up" if during_start else f"training, after {saves} "
                      "checkpoint writes", "resumes_from_step": readable_step(killed)})
        continue
    if process.wait() != 0:
      raise SystemExit(f"the resumed run failed with exit code {process.returncode}")
    break

  reference, resumed = leaves(work / "reference"), leaves(killed)
  identical = len(reference) == len(resumed) and all(
      a.shape == b.shape and np.array_equal(a, b) for a, b in zip(reference, resumed))
  leftovers = [path.name for path in killed.rglob(".*") if path.is_file()]
  result = {
      "what": "signerf train killed with SIGKILL at random moments and resumed until done; "
              "compared bit for bit with an uninterrupted run",
      "steps": STEPS, "checkpoint_every_steps": 1, "seed": args.seed,
      "uninterrupted_seconds": round(uninterrupted_seconds, 1),
      "kills": kills, "final_step": readable_step(killed),
      "identical_to_uninterrupted": identical,
      "max_abs_difference": max(float(np.max(np.abs(a - b), initial=0.0))
                                for a, b in zip(reference, resumed)),
      "temporary_files_left": leftovers,
      "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(),
                  "load_average_at_start": load_at_start,
                  "load_average_at_end": os.getloadavg(), **machine.code_version()},
  }
  args.results.mkdir(parents=True, exist_ok=True)
  files.write_json(args.results / "kill_resume.json", result)
  print(f"{len(kills)} kills; resumed run identical to the uninterrupted one: {identical}; "
        f"temporary files left: {leftovers or 'none'}")


if __name__ == "__main__":
  main()
