"""A phone capture without its poses: stitch's 110 images (../shared/data/stitch, train and test)
through `signerf process`, against the poses the capture came with.

  python experiments/process_capture.py [--out outputs/process_capture] [--train_seconds 300]

Steps, each the `signerf` command a user types, in a process of its own: `signerf process`
on a folder of the 110 images (links; the capture's transforms are not read) into OUT/data;
the recovered poses against the given ones after a similarity alignment (rotation error in
degrees, position error relative to the cameras' radius around their centre); then a NeRF
trained on the recovered poses and one on the given poses, same time budget and downscale (4:
200 px), both held out on stitch's 22 test views (the first with their recovered poses).
Writes into --results DIR (default outputs/experiments/) process_capture.json (registration,
errors, seconds per step, the two NeRFs' held-out PSNR/SSIM, the machine) and
process_capture.png (camera centres seen from above, given and recovered; a held-out view
rendered by the NeRF on recovered poses, by the one on given poses, and the photo).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from signerf_jax import files, ownership
from signerf_jax.data import pose_alignment

sys.path.insert(0, str(Path(__file__).resolve().parent))
import machine  # pylint: disable=wrong-import-position
import plotting  # pylint: disable=wrong-import-position
import results_dir  # pylint: disable=wrong-import-position

SHARED_DATA = Path(os.environ.get("SIGNERF_SHARED_DATA",
                                  Path(__file__).resolve().parents[2] / "shared" / "data"))
STITCH = SHARED_DATA / "stitch"
DOWNSCALE = 4  # 200 x 200 px views, as bench_nerf's stitch_200.


def signerf(*argv) -> tuple[float, str]:
  """Runs `signerf ARGV` in a new process: (wall seconds, its stdout). Fails on an error."""
  start = time.perf_counter()
  command = [sys.executable, "-m", "signerf_jax.cli", *map(str, argv)]
  done = subprocess.run(command, stdout=subprocess.PIPE, text=True, check=False)
  if done.returncode != 0:
    raise SystemExit(f"{' '.join(command)} failed with exit code {done.returncode}")
  return time.perf_counter() - start, done.stdout


def given_poses() -> dict[str, np.ndarray]:
  """Image name -> [4, 4] camera-to-world the capture came with (train and test)."""
  poses = {}
  for split in ("train", "test"):
    for frame in files.read_json(STITCH / f"transforms_{split}.json")["frames"]:
      poses[Path(frame["file_path"]).name + ".png"] = np.asarray(frame["transform_matrix"])
  return poses


def link_photos(folder: Path, names: list[str]) -> None:
  """`folder` holding a link to each of stitch's images (made anew; only links are removed)."""
  folder.mkdir(parents=True, exist_ok=True)
  for path in folder.iterdir():
    if path.is_symlink():
      path.unlink()
  for name in names:
    split = "test" if (STITCH / "test" / name).exists() else "train"
    (folder / name).symlink_to((STITCH / split / name).resolve())


def recovered_poses(data: Path) -> dict[str, np.ndarray]:
  """Image name -> [4, 4] camera-to-world `signerf process` recovered (DATA/transforms.json)."""
  return {Path(frame["file_path"]).name: np.asarray(frame["transform_matrix"])
          for frame in files.read_json(data / "transforms.json")["frames"]}


def pose_accuracy(data: Path, given: dict[str, np.ndarray]) -> dict:
  """Rotation and position errors of the recovered poses after a similarity alignment."""
  recovered = recovered_poses(data)
  names = sorted(recovered)
  rotation, position, radius = pose_alignment.pose_errors(
      np.stack([recovered[name] for name in names]), np.stack([given[name] for name in names]))
  relative = position / radius
  return {"rotation_degrees": {"median": float(np.median(rotation)),
                               "max": float(np.max(rotation))},
          "position_fraction_of_radius": {"median": float(np.median(relative)),
                                          "max": float(np.max(relative))},
          "radius_in_capture_units": radius}


def held_out(run: Path) -> dict:
  """The run's held-out PSNR/SSIM and training seconds (its eval.json)."""
  evaluation = files.read_json(run / "eval.json")
  return {"psnr": evaluation["held_out"]["psnr"], "ssim": evaluation["held_out"]["ssim"],
          "seconds_trained": evaluation["seconds_trained"]}


def camera_panel(data: Path, given: dict[str, np.ndarray]) -> np.ndarray:
  """Camera centres from above (x, y of the given frame), given and recovered (aligned)."""
  recovered = recovered_poses(data)
  names = sorted(recovered)
  estimated = np.stack([recovered[name][:3, 3] for name in names])
  truth = np.stack([given[name][:3, 3] for name in names])
  similarity = pose_alignment.similarity_from_points(estimated, truth)
  aligned = estimated @ similarity[:3, :3].T + similarity[:3, 3]
  series = [plotting.Series("given", truth[:, 0], truth[:, 1]),
            plotting.Series("recovered, aligned", aligned[:, 0], aligned[:, 1], dashed=True)]
  return plotting.line_chart("camera centres from above", series, "x", "y", y_from_zero=False)


def render_panel(runs: dict[str, Path], name: str) -> np.ndarray:
  """Held-out view `name`: each run's render (its eval/ folder) and the photo, side by side."""
  panels = []
  for run in runs.values():
    colour = [path for path in (run / "eval").glob(f"*{Path(name).stem}.png")]
    panels.append(files.read_image(colour[0])[..., :3])
  photo = files.read_image(STITCH / "test" / name)[..., :3]
  height, width = panels[0].shape[:2]
  panels.append(cv2.resize(photo, (width, height), interpolation=cv2.INTER_AREA))
  return np.concatenate(panels, axis=1)


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--out", type=Path, default=Path("outputs/process_capture"))
  parser.add_argument("--train_seconds", type=float, default=300.0)
  results_dir.add_argument(parser)
  args = parser.parse_args()
  measured_on = machine.record()
  given = given_poses()
  test_names = sorted(Path(frame["file_path"]).name + ".png" for frame in
                      files.read_json(STITCH / "transforms_test.json")["frames"])
  photos, data = args.out / "photos", args.out / "data"
  link_photos(photos, sorted(given))
  runs = {"recovered poses": args.out / "run_recovered", "given poses": args.out / "run_given"}
  ownership.clear(data, ownership.DATASET)
  for run in runs.values():
    ownership.clear(run, ownership.RUN)
  process_seconds, printed = signerf("process", "--images", photos, "--out", data)
  summary = json.loads(printed.strip().splitlines()[-1])
  held_out_list = args.out / "held_out.txt"
  held_out_list.write_text("".join(f"{name}\n" for name in test_names))
  train = ("--downscale", DOWNSCALE, "--max_seconds", args.train_seconds)
  signerf("train", "--data", data, "--run", runs["recovered poses"], "--held_out",
          f"@{held_out_list}", *train)
  signerf("train", "--data", STITCH, "--run", runs["given poses"], *train)
  nerfs = {label: held_out(run) for label, run in runs.items()}
  result = {
      "what": "stitch's 110 images processed without their poses (signerf process), the "
              "recovered poses against the given ones, and NeRFs trained on each",
      "machine": measured_on,
      "images": summary["images"], "registered": summary["registered"],
      "registered_fraction": summary["registered"] / summary["images"],
      "unregistered": summary["unregistered"], "matching": summary["matching"],
      "pairs": summary["pairs"], "mean_reprojection_error_px":
          summary["mean_reprojection_error_px"],
      "process_wall_seconds": process_seconds, "step_seconds": summary["seconds"],
      "pose_accuracy": pose_accuracy(data, given),
      "nerf": {"downscale": DOWNSCALE, "train_seconds_budget": args.train_seconds, **nerfs,
               "psnr_difference_db": nerfs["given poses"]["psnr"]
               - nerfs["recovered poses"]["psnr"]},
      "load_average_at_end": os.getloadavg(),
  }
  args.results.mkdir(parents=True, exist_ok=True)
  files.write_json(args.results / "process_capture.json", result)
  files.write_image(args.results / "process_capture.png", plotting.stacked([
      camera_panel(data, given)[..., ::-1] / 255.0, render_panel(runs, test_names[0])]))
  print(json.dumps({key: result[key] for key in (
      "registered", "process_wall_seconds", "pose_accuracy")} | {"nerf": result["nerf"]}))


if __name__ == "__main__":
  main()
