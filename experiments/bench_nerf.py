"""Speed against error of the NeRF on real captures and synthetic scenes: held-out PSNR against
training seconds, the generalisation gap to the training views, near-camera floaters and the
held-out depth's multi-view consistency (`metrics.depth_consistency`).

  python experiments/bench_nerf.py [--gin_file bench_nerf] [--gin_param 'bench_nerf.scenes = ["lego"]']

Scenes (in ../shared/data; `SIGNERF_SHARED_DATA` points elsewhere):
  stitch_200, stitch_400  the real 360-degree phone capture at 200^2 and 400^2, held out = its
                          test views (transforms_test.json);
  fern                    LLFF fern images_8 (504x378), every 8th view held out;
  lego                    Blender lego at 100^2, its 25 test views;
  lego_12                 the same with 12 training views (0, 8, ..., 88 of the 100);
  stitch_13               stitch at 200^2 with 13 training views (0, 7, ..., 84 of its 88).
Each trains once with the schedule spanning its longest time and is evaluated on its held-out
views at every time in `seconds`, and on 16 training views (the generalisation gap) at the last
(training time excludes evaluation; it includes compilation). Writes bench_nerf.{json,png,gin}
and bench_nerf_<scene>.png (held-out views: the photo, the render and its median depth) into
--results DIR (default outputs/experiments/); `--name STEM` writes STEM.* and STEM_<scene>.png.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import time
from pathlib import Path
from typing import Any, Sequence

import gin
import numpy as np

from signerf_jax import allocator, configs, files
from signerf_jax.data import load_dataset
from signerf_jax.editing import figures
from signerf_jax.nerf import capacity, evaluate, render, train, training_run

import machine  # experiments/machine.py and plotting.py (this script's directory is on sys.path)
import plotting
import results_dir

SHARED_DATA = Path(os.environ.get("SIGNERF_SHARED_DATA",
                                  Path(__file__).resolve().parents[2] / "shared" / "data"))


@dataclasses.dataclass(frozen=True)
class Scene:
  """A benchmark scene: where it is, how it is read, and which training views are kept."""

  path: Path
  downscale: int
  training_views: tuple[int, ...] | None = None  # None: all of the train split.


SCENES = {
    "stitch_200": Scene(SHARED_DATA / "stitch", 4),
    "stitch_400": Scene(SHARED_DATA / "stitch", 2),
    "fern": Scene(SHARED_DATA / "llff" / "fern", 8),
    "lego": Scene(SHARED_DATA / "nerf_synthetic" / "lego", 8),
    "lego_12": Scene(SHARED_DATA / "nerf_synthetic" / "lego", 8, tuple(range(0, 96, 8))),
    "stitch_13": Scene(SHARED_DATA / "stitch", 4, tuple(range(0, 88, 7))),
}
FIGURE_VIEWS = 3


def load_scene(name: str):
  """(train, held-out) datasets of a benchmark scene."""
  scene = SCENES[name]
  if not scene.path.is_dir():
    raise FileNotFoundError(f"benchmark scene {name} needs {scene.path}")
  training = load_dataset(scene.path, split="train", downscale=scene.downscale)
  if scene.training_views is not None:
    training = training.subset(list(scene.training_views))
  return training, load_dataset(scene.path, split="eval", downscale=scene.downscale)


def figure(held_out, renders) -> np.ndarray:
  """Rows of held-out views: photo, render, median depth."""
  views = np.linspace(0, held_out.num_images - 1, FIGURE_VIEWS).round().astype(int)
  rows = [[held_out.images[i], renders["rgb"][i], render.depth_image(renders["median_depth"][i])]
          for i in views]
  labels = [[f"{held_out.image_names[i]}", "render", "median depth"] for i in views]
  return figures.image_grid(rows, labels)


def train_and_measure(name: str, seconds: Sequence[float], figure_path: Path,
                      config: train.TrainConfig, rules: capacity.CapacityRules,
                      supersampling: int | None = None) -> dict[str, Any]:
  """Trains `name` (sized by `rules`) with the schedule spanning max(seconds), evaluating at
  each time; held-out views (`figure`) go to `figure_path`. With `supersampling`, the held-out
  views are also rendered at the last time with that many rays per pixel side
  ("held_out_supersampled", and the seconds that rendering took)."""
  seconds = sorted(seconds)
  training, held_out = load_scene(name)
  model = training_run.build_model(training, rules=rules)
  config = dataclasses.replace(config, max_seconds=seconds[-1], steps=1_000_000_000)
  trainer = training_run.make_trainer(training, model=model, config=config)
  curve, renders = [], None
  for limit in seconds:
    trainer.run(until_seconds=limit, progress=False)
    started = time.perf_counter()
    point = {"seconds": trainer.seconds_trained, "step": trainer.step}
    if limit == seconds[-1]:
      report, renders = evaluate.generalisation_report(model, trainer.state.variables, held_out,
                                                       training)
      point.update(held_out=report["held_out"], train=report["train"],
                   generalisation_gap_db=report["generalisation_gap_db"])
      if supersampling is not None:
        rendering_started = time.perf_counter()
        point["held_out_supersampled"], _ = evaluate.evaluate(
            model, trainer.state.variables, held_out, supersampling=supersampling)
        point["supersampled_eval_seconds"] = time.perf_counter() - rendering_started
    else:
      # The training views are rendered only at the end: at 400^2 they would double the time
      # spent evaluating.
      point["held_out"], renders = evaluate.evaluate(model, trainer.state.variables, held_out)
    point["eval_seconds"] = time.perf_counter() - started
    curve.append(point)
    held_out_metrics = point["held_out"]
    train_psnr = f", train {point['train']['psnr']:.2f} dB" if "train" in point else ""
    supersampled = (f", {supersampling}x{supersampling} rays a pixel "
                    f"{point['held_out_supersampled']['psnr']:.2f} dB"
                    if "held_out_supersampled" in point else "")
    print(f"[{name}] {point['seconds']:.0f} s, step {point['step']}: held-out "
          f"{held_out_metrics['psnr']:.2f} dB / SSIM {held_out_metrics['ssim']:.3f}{train_psnr}"
          f"{supersampled}, near-camera weight {held_out_metrics['near_camera_weight']:.4f}, "
          f"depth consistency {held_out_metrics['depth_consistency']:.3f}",
          flush=True)
  files.write_image(figure_path, figure(held_out, renders))
  rays = trainer.step * model.capacity.rays_per_batch
  return {
      "train_views": training.num_images, "held_out_views": held_out.num_images,
      "image_size": [training.width, training.height],
      "frame": training.frame,
      "curve": curve,
      "held_out_psnr_at_seconds": {str(int(limit)): point["held_out"]["psnr"]
                                   for limit, point in zip(seconds, curve)},
      "generalisation_gap_db": curve[-1]["generalisation_gap_db"],
      "training_samples_per_second": trainer.samples_trained / max(trainer.seconds_trained, 1e-9),
      "training_rays_per_second": rays / max(trainer.seconds_trained, 1e-9),
      "steps_per_second": trainer.step / max(trainer.seconds_trained, 1e-9),
      "capacity": dataclasses.asdict(model.capacity),
  }


@gin.configurable("bench_nerf")
def run_benchmark(scenes: Sequence[str] = tuple(SCENES),
                  seconds: dict[str, Sequence[float]] | None = None,
                  machine_shared: bool = False,
                  output_stem: str = "bench_nerf",
                  results: Path = results_dir.DEFAULT,
                  supersampling: dict[str, int] | None = None) -> dict[str, Any]:
  """Runs every scene.

  Args:
    scenes: names from SCENES.
    seconds: per scene, the training times at which to evaluate.
    machine_shared: record whether other jobs shared the CPU (timings are then pessimistic).
    output_stem: <results>/<stem>_<scene>.png holds each scene's held-out views, and
      <results>/<stem>.partial.json the result so far after every scene.
    results: the folder written into.
    supersampling: per scene, rays per pixel side of a second held-out evaluation at the last
      time (`render.render_cameras`; anti-aliasing at that many squared times the rendering).
  """
  seconds, supersampling = dict(seconds or {}), dict(supersampling or {})
  config, rules = configs.build(train.TrainConfig), configs.build(capacity.CapacityRules)
  result: dict[str, Any] = {
      "machine": machine.record(processor=platform.processor(),
                                shared_with_other_jobs=machine_shared),
      "train_config": dataclasses.asdict(config),
      "scenes": {},
  }
  for name in scenes:
    result["scenes"][name] = train_and_measure(name, seconds.get(name, (60, 120, 300, 600)),
                                               results / f"{output_stem}_{name}.png", config,
                                               rules, supersampling.get(name))
    files.write_json(results / f"{output_stem}.partial.json", result)
  result["load_average_at_end"] = os.getloadavg()
  return result


def plot(result: dict[str, Any], path: Path) -> None:
  """Held-out PSNR against training seconds, one line per scene."""
  series = [plotting.Series(name, [point["seconds"] for point in scene["curve"]],
                            [point["held_out"]["psnr"] for point in scene["curve"]])
            for name, scene in result["scenes"].items()]
  plotting.write_panels(path, [plotting.line_chart(
      "NeRF: held-out PSNR against training time", series, "training seconds on this machine",
      "held-out PSNR (dB)", width=900, height=560, y_from_zero=False)])


def main() -> None:
  allocator.keep_freed_memory()  # As `signerf train` and `signerf render` do.
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  configs.add_gin_arguments(parser)
  parser.add_argument("--name", default="bench_nerf", help="output file stem in DIR")
  results_dir.add_argument(parser)
  args = parser.parse_args()
  configs.parse_gin(["bench_nerf", *args.gin_file], args.gin_param)
  result = run_benchmark(output_stem=args.name, results=args.results)
  files.write_text(args.results / f"{args.name}.gin", gin.config_str())
  files.write_json(args.results / f"{args.name}.json", result)
  plot(result, args.results / f"{args.name}.png")
  (args.results / f"{args.name}.partial.json").unlink(missing_ok=True)
  print(f"bench_nerf: results in {args.results / args.name}.json and .png")


if __name__ == "__main__":
  main()
