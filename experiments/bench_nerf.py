"""Speed against error of the NeRF on this machine: PSNR (and depth error) against wall-clock
training time on a synthetic scene, Blender lego at 100x100 and LLFF fern (images_16), plus what
the derived capacity buys against a fixed large configuration.

  python experiments/bench_nerf.py [--gin_file bench_nerf] [--gin_param 'bench_nerf.scenes = ["lego"]']

Writes experiments/results/bench_nerf.json, bench_nerf.png and bench_nerf.gin (the full config).
Training time excludes evaluation; it includes compilation and occupancy-grid updates.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import tempfile
import time
from pathlib import Path
from typing import Any, Sequence

import gin
import jax

from signerf_jax import configs, files
from signerf_jax.data import load_dataset, synthetic
from signerf_jax.nerf import evaluate, train
from signerf_jax.nerf.model import NerfModel

import plotting  # experiments/plotting.py (this script's directory is on sys.path)

RESULTS = Path(__file__).resolve().parent / "results"
SHARED_DATA = Path(os.environ.get("SIGNERF_SHARED_DATA",
                                  Path(__file__).resolve().parents[2] / "shared" / "data"))
# How each benchmark scene is read: (path or None for the generated scene, downscale).
SCENES = {
    "synthetic": (None, 1),
    "lego": (SHARED_DATA / "nerf_synthetic" / "lego", 8),
    "fern": (SHARED_DATA / "llff" / "fern", 16),
}


def load_scene(name: str, workdir: Path):
  """(train, eval) datasets of a benchmark scene."""
  root, downscale = SCENES[name]
  if root is None:
    root = workdir / "synthetic"
    synthetic.generate(root, seed=0)
  if not Path(root).is_dir():
    raise FileNotFoundError(f"benchmark scene {name} needs {root}")
  return (load_dataset(root, split="train", downscale=downscale),
          load_dataset(root, split="eval", downscale=downscale))


def train_and_measure(train_set, eval_set, model: NerfModel, seconds: Sequence[float],
                      label: str) -> dict[str, Any]:
  """Trains in bursts up to each time in `seconds`, evaluating on `eval_set` after each."""
  config = train.TrainConfig()
  trainer = train.make_trainer(train_set, model=model, config=config)
  curve = []
  for limit in seconds:
    statistics = trainer.run(until_step=config.steps * 100, until_seconds=limit, progress=False)
    started = time.perf_counter()
    metrics, _ = evaluate.evaluate(model, trainer.state.variables, eval_set)
    point = {"seconds": trainer.seconds_trained, "step": trainer.step, **metrics,
             "batch_psnr": statistics.get("psnr"),
             "eval_seconds": time.perf_counter() - started}
    curve.append(point)
    print(f"[{label}] {point['seconds']:.0f} s, step {point['step']}: "
          f"{point['psnr']:.2f} dB, ssim {point['ssim']:.3f}, depth_mae {point['depth_mae']}",
          flush=True)
  return {
      "curve": curve,
      "psnr_at_seconds": {str(int(limit)): point["psnr"] for limit, point in zip(seconds, curve)},
      "samples_per_second": trainer.samples_trained / max(trainer.seconds_trained, 1e-9),
      "steps_per_second": trainer.step / max(trainer.seconds_trained, 1e-9),
      "capacity": dataclasses.asdict(model.capacity),
  }


@gin.configurable("bench_nerf")
def run_benchmark(scenes: Sequence[str] = ("synthetic", "lego", "fern"),
                  seconds: Sequence[float] = (60, 120, 300, 600),
                  comparison_scene: str = "lego",
                  comparison_seconds: Sequence[float] = (60, 120, 300),
                  fixed_large_capacity: dict[str, Any] | None = None,
                  machine_shared: bool = True,
                  progress_path: Path | None = None) -> dict[str, Any]:
  """Runs every scene, then derived-vs-fixed-large capacity on `comparison_scene`.

  Args:
    scenes: names from SCENES.
    seconds: training times at which to evaluate.
    comparison_scene, comparison_seconds: where and how long to compare capacities.
    fixed_large_capacity: Capacity overrides of the fixed large configuration (instant-NGP's
      defaults: 16 levels, 16..2048, 2^19 rows); None skips the comparison.
    machine_shared: record whether other jobs shared the CPU (timings are then pessimistic).
    progress_path: if given, the partial result is written there after every scene.
  """
  result: dict[str, Any] = {
      "machine": {"platform": platform.platform(), "processor": platform.processor(),
                  "cpu_count": os.cpu_count(), "jax": jax.__version__,
                  "shared_with_other_jobs": machine_shared,
                  "load_average_at_start": os.getloadavg()},
      "scenes": {},
  }
  with tempfile.TemporaryDirectory() as workdir:
    for name in scenes:
      train_set, eval_set = load_scene(name, Path(workdir))
      model = train.build_model(train_set)
      result["scenes"][name] = {
          "train_views": train_set.num_images, "eval_views": eval_set.num_images,
          "image_size": [train_set.width, train_set.height],
          **train_and_measure(train_set, eval_set, model, seconds, name)}
      if progress_path is not None:
        files.write_json(progress_path, result)
    if fixed_large_capacity is not None:
      train_set, eval_set = load_scene(comparison_scene, Path(workdir))
      derived = train.build_model(train_set)
      large = NerfModel(derived.scene, dataclasses.replace(derived.capacity,
                                                           **fixed_large_capacity))
      result["capacity_comparison"] = {"scene": comparison_scene}
      for label, model in (("derived", derived), ("fixed_large", large)):
        measured = train_and_measure(train_set, eval_set, model, comparison_seconds,
                                     f"{comparison_scene}/{label}")
        result["capacity_comparison"][label] = measured
  result["load_average_at_end"] = os.getloadavg()
  return result


def plot(result: dict[str, Any], path: Path) -> None:
  """PSNR against training seconds, one line per scene and per capacity of the comparison."""
  lines = [(name, scene["curve"]) for name, scene in result["scenes"].items()]
  comparison = result.get("capacity_comparison")
  if comparison:
    for label in ("derived", "fixed_large"):
      lines.append((f"{comparison['scene']} ({label} capacity)", comparison[label]["curve"]))
  series = [plotting.Series(label, [point["seconds"] for point in curve],
                            [point["psnr"] for point in curve]) for label, curve in lines]
  plotting.write_panels(path, [plotting.line_chart(
      "NeRF: speed against error", series, "training seconds on this machine", "PSNR (dB)",
      width=900, height=560, y_from_zero=False)])


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--gin_file", action="append", default=["bench_nerf"])
  parser.add_argument("--gin_param", action="append", default=[])
  parser.add_argument("--name", default="bench_nerf", help="output file stem in results/")
  args = parser.parse_args()
  configs.parse_gin(args.gin_file, args.gin_param)
  result = run_benchmark(progress_path=RESULTS / f"{args.name}.partial.json")
  files.write_text(RESULTS / f"{args.name}.gin", gin.config_str())
  files.write_json(RESULTS / f"{args.name}.json", result)
  plot(result, RESULTS / f"{args.name}.png")
  (RESULTS / f"{args.name}.partial.json").unlink(missing_ok=True)
  print(f"bench_nerf: results in {RESULTS / args.name}.json and .png")


if __name__ == "__main__":
  main()
