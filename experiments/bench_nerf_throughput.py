"""Training and rendering throughput of trained NeRFs: rays and field samples per second, with
the held-out PSNR of what was rendered, so that speed is reported with its error.

  python experiments/bench_nerf_throughput.py --run lego=RUN_DIR --run stitch_200=RUN_DIR \
      [--views 4] [--train_steps 40] [--render_sample_fraction F ...] [--whole_march N] \
      [--name bench_nerf_throughput]

For each run (a `signerf train` directory):
  * rendering: its first `views` held-out views with the renderer the viewer, the views stage and
    the evaluation use (`nerf.render`, chunks of 4096 rays), timed the second time (the first
    compiles); rays/s, field samples per ray and per second (every network evaluation: the
    proposal networks' too, and with the occupancy sampler only the occupied samples), and the
    views' PSNR; with `--render_sample_fraction`, also at each of those fractions of the
    radiance field's samples (`Capacity.render_sample_fraction`), side by side; with
    `--whole_march N`, N times in turn with and without the occupancy sampler's short march
    (`ray_samples.render_march`; without it every ray marches through the whole scene box, as
    before), in the same process, so that a noisy machine slows both alike;
  * training: `train_steps` steps from its checkpoint on its training views, after
    `warmup_steps` untimed ones (compilation); rays/s and field samples/s.
Writes <name>.json with the machine and its load into --results DIR (default
outputs/experiments/).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import os
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np

from signerf_jax import allocator, camera, files
from signerf_jax.metrics import image as image_metrics
from signerf_jax.nerf import evaluate, ray_samples, render, train, training_run
from signerf_jax.nerf import model as nerf_model
from signerf_jax.nerf.commands import load_recorded_dataset

import machine  # experiments/machine.py (this script's directory is on sys.path)
import results_dir

CHUNK_SIZE = 4096


@functools.partial(jax.jit, static_argnums=(0,))
def _samples_in_chunk(model: nerf_model.NerfModel, variables, chunk: camera.Rays):
  """Field samples a rendering chunk evaluates (occupied ones only with the occupancy sampler)."""
  _, aux = nerf_model.render_rays(model, variables, chunk, jax.random.PRNGKey(0), training=False)
  return aux["samples_evaluated"]


def render_samples_per_ray(model, variables, cameras, indices) -> float:
  """Mean field samples per ray over the whole chunks of the views `indices`."""
  samples = rays = 0
  for index in indices:
    flat = jax.tree.map(lambda a: np.asarray(a).reshape((-1,) + np.asarray(a).shape[2:]),
                        render.image_rays(cameras, int(index)))
    for start in range(0, flat.shape[0] - CHUNK_SIZE + 1, CHUNK_SIZE):
      chunk = jax.tree.map(lambda a: a[start:start + CHUNK_SIZE], flat)  # pylint: disable=cell-var-from-loop
      samples += int(_samples_in_chunk(model, variables, chunk))
      rays += CHUNK_SIZE
  return samples / max(rays, 1)


def measure_rendering(run, held_out, views: int) -> dict[str, Any]:
  indices = range(min(views, held_out.num_images))
  cameras = held_out.cameras.take(list(indices))
  render.render_cameras(run.model, run.variables, cameras, CHUNK_SIZE)  # Compiles.
  started = time.perf_counter()
  renders = render.render_cameras(run.model, run.variables, cameras, CHUNK_SIZE)
  seconds = time.perf_counter() - started
  rays = len(indices) * held_out.width * held_out.height
  per_ray = render_samples_per_ray(run.model, run.variables, held_out.cameras, indices)
  psnr = np.mean([float(image_metrics.psnr_jit(renders["rgb"][i], held_out.images[index]))
                  for i, index in enumerate(indices)])
  return {"views": len(indices), "image_size": [held_out.width, held_out.height],
          "seconds": seconds, "rays_per_second": rays / seconds,
          "field_samples_per_ray": per_ray, "field_samples_per_second": rays * per_ray / seconds,
          "held_out_psnr": float(psnr)}


def measure_training(run, training, warmup_steps: int, steps: int) -> dict[str, Any]:
  config = dataclasses.replace(train.TrainConfig(), steps=warmup_steps + steps)
  trainer = training_run.make_trainer(training, model=run.model, config=config,
                                      init_variables=run.variables)
  trainer.run(until_step=warmup_steps, progress=False)
  samples_before, started = trainer.samples_trained, time.perf_counter()
  trainer.run(until_step=warmup_steps + steps, progress=False)
  seconds = time.perf_counter() - started
  rays = steps * run.model.capacity.rays_per_batch
  return {"steps": steps, "rays_per_batch": run.model.capacity.rays_per_batch,
          "seconds": seconds, "steps_per_second": steps / seconds,
          "rays_per_second": rays / seconds,
          "field_samples_per_second": (trainer.samples_trained - samples_before) / seconds}


@contextlib.contextmanager
def whole_march():
  """Renders marching every step through the scene box (no `ray_samples.render_march`; the
  renderer's own lookup of it is replaced, as it reuses the last one)."""
  short_march = render._occupied_march  # pylint: disable=protected-access
  render._occupied_march = lambda model, variables: None  # pylint: disable=protected-access
  try:
    yield
  finally:
    render._occupied_march = short_march  # pylint: disable=protected-access


def compare_with_whole_march(run, held_out, views: int, repeats: int) -> dict[str, Any]:
  """Rendering with and without the short march, `repeats` times in turn."""
  measured: dict[str, list[dict[str, Any]]] = {"short_march": [], "whole_march": []}
  for _ in range(repeats):
    measured["short_march"].append(measure_rendering(run, held_out, views))
    with whole_march():
      measured["whole_march"].append(measure_rendering(run, held_out, views))
  result = {name: {"rays_per_second": [point["rays_per_second"] for point in points],
                   "held_out_psnr": points[0]["held_out_psnr"]}
            for name, points in measured.items()}
  result["speedups"] = [short / whole for short, whole in zip(
      result["short_march"]["rays_per_second"], result["whole_march"]["rays_per_second"])]
  result["median_speedup"] = float(np.median(result["speedups"]))
  return result


def measure_run(run_dir: Path, views: int, warmup_steps: int, steps: int,
                render_sample_fractions: tuple[float, ...] = (),
                whole_march_repeats: int = 0) -> dict[str, Any]:
  run = evaluate.load_run(run_dir)
  held_out = load_recorded_dataset(run.description, "eval")
  training = load_recorded_dataset(run.description, "train")
  capacity = run.model.capacity
  at_fractions = {}
  for fraction in render_sample_fractions:
    model = dataclasses.replace(run.model, capacity=dataclasses.replace(
        capacity, render_sample_fraction=fraction))
    at_fractions[f"{fraction:g}"] = measure_rendering(dataclasses.replace(run, model=model),
                                                      held_out, views)
  return {"run": str(run_dir), "scene_kind": run.model.scene.kind, "sampler": capacity.sampler,
          "proposal_samples": list(capacity.proposal_samples),
          "samples_per_ray": capacity.samples_per_ray,
          "render_sample_fraction": capacity.render_sample_fraction, "step_trained": run.step,
          "march_steps": capacity.march_steps,
          "render_march_steps": getattr(ray_samples.render_march(run.model, run.variables),
                                        "steps", None),
          "rendering": measure_rendering(run, held_out, views),
          "rendering_at_sample_fraction": at_fractions,
          "whole_march_comparison": (compare_with_whole_march(run, held_out, views,
                                                              whole_march_repeats)
                                     if whole_march_repeats else None),
          "training": measure_training(run, training, warmup_steps, steps)}


def main() -> None:
  allocator.keep_freed_memory()  # As `signerf train` and `signerf render` do.
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--run", action="append", required=True, metavar="NAME=RUN_DIR",
                      help="a trained run to measure (repeatable)")
  parser.add_argument("--views", type=int, default=4, help="held-out views rendered per run")
  parser.add_argument("--warmup_steps", type=int, default=5)
  parser.add_argument("--train_steps", type=int, default=40)
  parser.add_argument("--render_sample_fraction", type=float, action="append", default=[],
                      help="also render at this Capacity.render_sample_fraction (repeatable)")
  parser.add_argument("--whole_march", type=int, default=0, metavar="N",
                      help="also compare with the occupancy sampler's whole march, N times in "
                           "turn")
  parser.add_argument("--name", default="bench_nerf_throughput", help="results/<name>.json")
  results_dir.add_argument(parser)
  args = parser.parse_args()
  result: dict[str, Any] = {
      "machine": machine.record(),
      "chunk_size": CHUNK_SIZE, "runs": {}}
  for entry in args.run:
    name, _, run_dir = entry.partition("=")
    result["runs"][name] = measure_run(Path(run_dir), args.views, args.warmup_steps,
                                       args.train_steps, tuple(args.render_sample_fraction),
                                       args.whole_march)
    print(name, result["runs"][name], flush=True)
  result["load_average_at_end"] = os.getloadavg()
  files.write_json(args.results / f"{args.name}.json", result)
  print(f"bench_nerf_throughput: results in {args.results / args.name}.json")


if __name__ == "__main__":
  main()
