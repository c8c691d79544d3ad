"""How fast `signerf view` shows a trained NeRF: seconds from a new camera to its first (coarse)
frame and to each finer one, and the rays per second behind them.

  python experiments/bench_viewer.py --runs RUN [RUN ...] [--name bench_viewer]

For each run (`signerf train`'s directory) the viewer's own renderer (`viewer.progressive`)
renders `--views` poses of the run's training cameras with a 16:9 canvas at the viewer's frame
heights, after one warm-up view (compilation: reported apart, as `first_view_seconds`).
Writes NAME.json (with the machine and its load) and NAME.png (one view's frames, coarse to
fine, per run) into --results DIR (default outputs/experiments/).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import time
from pathlib import Path

import cv2
import jax
import numpy as np

from signerf_jax import files
from signerf_jax.editing import figures
from signerf_jax.nerf import evaluate
from signerf_jax.nerf.commands import load_recorded_dataset
from signerf_jax.viewer import progressive
from signerf_jax.viewer.cameras import pose_of_camera

import machine  # experiments/machine.py (this script's directory is on sys.path)
import results_dir  # experiments/results_dir.py (this script's directory is on sys.path)

CANVAS_ASPECT = 16 / 9


def frame_seconds(run, poses) -> tuple[list[list[float]], list[progressive.Frame]]:
  """Seconds to each frame height for every pose ([poses][heights]), and the last pose's
  frames."""
  seconds, frames = [], []
  for pose in poses:
    frames = list(progressive.render_progressively(run.model, run.variables, pose,
                                                   lambda: True))
    seconds.append([frame.seconds for frame in frames])
  return seconds, frames


def bench_run(run_dir: Path, views: int) -> tuple[dict, list[progressive.Frame]]:
  run = evaluate.load_run(run_dir)
  cameras = load_recorded_dataset(run.description, "train").cameras
  indices = np.linspace(0, cameras.num_cameras - 1, views + 1).round().astype(int)
  poses = [dataclasses.replace(pose_of_camera(cameras, int(index)), aspect=CANVAS_ASPECT)
           for index in indices]
  start = time.perf_counter()
  list(progressive.render_progressively(run.model, run.variables, poses[0], lambda: True))
  first_view = time.perf_counter() - start
  seconds, frames = frame_seconds(run, poses[1:])
  median = np.median(np.asarray(seconds), axis=0)
  pixels = [frame.rgb.shape[0] * frame.rgb.shape[1] for frame in frames]
  increments = np.diff(np.concatenate([[0.0], median]))
  return {
      "run": str(run_dir), "scene_kind": run.model.scene.kind,
      "sampler": run.model.capacity.sampler,
      "first_view_seconds": round(first_view, 3),
      "views": len(poses) - 1,
      "frames": [{"height": frame.rgb.shape[0], "width": frame.rgb.shape[1],
                  "seconds_to_frame": round(float(total), 3),
                  "rays_per_second": round(count / float(step))}
                 for frame, total, count, step in zip(frames, median, pixels, increments)],
  }, frames


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--runs", nargs="+", required=True, help="trained run directories")
  parser.add_argument("--views", type=int, default=5, help="timed views per run")
  parser.add_argument("--name", default="bench_viewer", help="results file stem")
  results_dir.add_argument(parser)
  args = parser.parse_args()
  load_before = os.getloadavg()
  results, rows, labels = [], [], []
  for run_dir in map(Path, args.runs):
    result, frames = bench_run(run_dir, args.views)
    results.append(result)
    print(result, flush=True)
    height, width = frames[-1].rgb.shape[:2]
    rows.append([cv2.resize(frame.rgb, (width, height), interpolation=cv2.INTER_NEAREST)
                 for frame in frames])
    labels.append([f"{run_dir.parent.name}/{run_dir.name}: {frame.rgb.shape[0]} px, "
                   f"{frame.seconds:.2f} s" for frame in frames])
  args.results.mkdir(parents=True, exist_ok=True)
  files.write_json(args.results / f"{args.name}.json", {
      "machine": {"platform": platform.platform(), "processor": platform.processor(),
                  "cpu_count": os.cpu_count(), "jax_devices": str(jax.devices()),
                  "load_average_before": load_before, "load_average_after": os.getloadavg(),
                  **machine.code_version()},
      "heights": list(progressive.HEIGHTS), "chunk_size": progressive.CHUNK_SIZE,
      "canvas_aspect": CANVAS_ASPECT, "runs": results})
  files.write_image(args.results / f"{args.name}.png", figures.image_grid(rows, labels))


if __name__ == "__main__":
  main()
