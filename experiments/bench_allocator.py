"""What keeping freed memory (`signerf_jax.allocator`) saves: the same work in fresh processes with
glibc's default allocator and with the setting that `signerf train`, `finetune`, `render`, `eval`,
`edit`, `demo` and `view` apply, alternating, so a busy machine slows both alike; and, as a third
mode, glibc's defaults with its memory in transparent huge pages (`GLIBC_TUNABLES=
glibc.malloc.hugetlb=1`: the same frees, 512x fewer page faults when the memory comes back).

  python experiments/bench_allocator.py \
      [--workloads nerf_train nerf_budget nerf_render unet_forward update] [--rounds 2] \
      [--modes glibc_default keep_freed_memory huge_pages] \
      [--nerf_steps 300] [--budget_seconds 300] [--name bench_allocator]
  python experiments/bench_allocator.py --workloads nerf_eval viewer_frames --run RUN

Workloads (each child process runs one and reports it as one JSON line):
  * nerf_train: `signerf train` on Blender lego at 100 px for `nerf_steps` steps; its training
    seconds (compilation and checkpoint writes excluded) and held-out PSNR;
  * nerf_budget: `signerf train --max_seconds budget_seconds` on the same lego: the steps it
    reaches and their held-out PSNR (what a time-budgeted user gets);
  * nerf_render: `signerf render --split all` of a lego run trained 50 steps first (untimed):
    the command's wall seconds (its compilation included) and a checksum of the images;
  * unet_forward: an SD 1.5-shaped UNet (random weights, batch 2, latent 64 x 64), the median of
    three jitted forwards after the one that compiles, and a checksum of its output;
  * update: the image set update with the shipped model (one view per call, 2 x 3 sheet), seconds
    per view over four views after the call that compiles;
and, only when asked for, on a trained run (`--run`, a `signerf train` directory):
  * nerf_eval: `signerf eval` on a copy of the run: the command's wall seconds (its compilation
    included) and the held-out PSNR it reports;
  * viewer_frames: `signerf view`'s progressive frames of five training poses after one that
    compiles (`bench_viewer.bench_run`): the median seconds to the finest frame, and a checksum
    of the last one.
Per child: wall seconds of the work, the process's user and system CPU seconds and minor page
faults over it, and its peak resident memory. Writes NAME.json with the machine and its load,
and NAME.png: each workload's speed-up, into --results DIR (default outputs/experiments/).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from signerf_jax import allocator, cli, files
from signerf_jax.diffusion import model_configs, weights
from signerf_jax.diffusion.pipeline import GenerationOptions
from signerf_jax.diffusion.unet import UNet2DCondition
from signerf_jax.editing import generation
from signerf_jax.editing import update as image_set_update
from signerf_jax.editing.config import DEFAULT_MODEL_DIR
from signerf_jax.editing.sheet import SheetLayout

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_update  # pylint: disable=wrong-import-position
import bench_viewer  # pylint: disable=wrong-import-position
import machine  # pylint: disable=wrong-import-position
import plotting  # pylint: disable=wrong-import-position
import results_dir  # pylint: disable=wrong-import-position
from bench_diffusion import SD15_UNET  # pylint: disable=wrong-import-position

LEGO = Path(os.environ.get("SIGNERF_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" /
                          "data")) / "nerf_synthetic" / "lego"
# Each mode's environment: glibc's defaults; `allocator.keep_freed_memory`; or glibc's defaults
# with malloc's memory in transparent huge pages (glibc >= 2.35 `hugetlb` tunable, read when the
# process starts), so that a fresh block faults in once a 2-MiB page instead of once a 4 KiB one.
MODES = {"glibc_default": {allocator.ENVIRONMENT_VARIABLE: "0"},
         "keep_freed_memory": {allocator.ENVIRONMENT_VARIABLE: "1"},
         "huge_pages": {allocator.ENVIRONMENT_VARIABLE: "0",
                        "GLIBC_TUNABLES": "glibc.malloc.hugetlb=1"}}
DEFAULT_WORKLOADS = ("nerf_train", "nerf_budget", "nerf_render", "unet_forward", "update")
RUN_WORKLOADS = ("nerf_eval", "viewer_frames")  # They need a trained run (--run).
WORKLOADS = (*DEFAULT_WORKLOADS, *RUN_WORKLOADS)
VIEWER_VIEWS = 5


def signerf(*arguments: str) -> None:
  status = cli.main(list(arguments))
  if status:
    raise RuntimeError(f"signerf {arguments[0]} exited with {status}")


def train_lego(out: Path, *options: str) -> dict[str, Any]:
  """Trains lego at 100 px into `out` with `signerf train` options; returns its eval.json."""
  signerf("train", "--data", str(LEGO), "--run", str(out), "--downscale", "8", *options)
  return json.loads((out / "eval.json").read_text())


def nerf_train(steps: int) -> dict[str, Any]:
  with tempfile.TemporaryDirectory() as directory:
    evaluation = train_lego(Path(directory) / "run", "--gin_param", f"TrainConfig.steps = {steps}")
  return {"seconds": evaluation["seconds_trained"],
          "result": round(evaluation["held_out"]["psnr"], 6)}


def nerf_budget(budget_seconds: float) -> dict[str, Any]:
  with tempfile.TemporaryDirectory() as directory:
    evaluation = train_lego(Path(directory) / "run", "--max_seconds", str(budget_seconds))
  return {"seconds": evaluation["seconds_trained"], "steps": evaluation["step"],
          "result": round(evaluation["held_out"]["psnr"], 6)}


def nerf_render() -> dict[str, Any]:
  with tempfile.TemporaryDirectory() as directory:
    run, renders = Path(directory) / "run", Path(directory) / "renders"
    train_lego(run, "--gin_param", "TrainConfig.steps = 50")
    started = time.perf_counter()
    signerf("render", "--run", str(run), "--out", str(renders), "--split", "all")
    seconds = time.perf_counter() - started
    digest = hashlib.sha256()
    for image in sorted(renders.rglob("*.png")):
      digest.update(image.read_bytes())
  return {"seconds": seconds, "result": digest.hexdigest()[:16]}


def unet_forward() -> dict[str, Any]:
  unet = UNet2DCondition(model_configs.UNetConfig.from_dict(SD15_UNET))
  params = weights.random_params(unet)
  rng = np.random.default_rng(0)
  arguments = (params, jnp.asarray(rng.standard_normal((2, 64, 64, 4)), jnp.float32),
               jnp.full((2,), 500), jnp.asarray(rng.standard_normal((2, 77, 768)), jnp.float32))
  forward = jax.jit(lambda params, sample, timesteps, context: unet.apply(
      {"params": params}, sample, timesteps, context))
  output = forward(*arguments).block_until_ready()  # Compiles.
  seconds = []
  for _ in range(3):
    started = time.perf_counter()
    forward(*arguments).block_until_ready()
    seconds.append(time.perf_counter() - started)
  return {"seconds": statistics.median(seconds),
          "result": round(float(jnp.sum(jnp.abs(output))), 3)}


def update() -> dict[str, Any]:
  model = str(DEFAULT_MODEL_DIR)
  tile = generation.native_tile_size(model)
  rng = np.random.default_rng(0)
  views = bench_update.random_views(4, tile, rng)
  sheet_rgb = rng.random((2 * tile, 3 * tile, 3), np.float32)
  sheet_control = rng.random((2 * tile, 3 * tile, 1), np.float32)
  generator = generation.load_generator(model, "", "", "a red cow", "",
                                        GenerationOptions(guidance_scale=5.0), 1)
  edit_batch = image_set_update.batch_editor(generator, SheetLayout(2, 3, -1, -1, tile, tile),
                                             "sheet", sheet_rgb, sheet_control)
  return {"seconds": bench_update.seconds_per_view(edit_batch, views, 1), "result": None}


def nerf_eval(run: Path) -> dict[str, Any]:
  with tempfile.TemporaryDirectory() as directory:
    copy = shutil.copytree(run, Path(directory) / "run")  # eval writes into the run.
    started = time.perf_counter()
    signerf("eval", "--run", str(copy))
    seconds = time.perf_counter() - started
    report = json.loads((copy / "eval.json").read_text())
  return {"seconds": seconds, "result": round(report["held_out"]["psnr"], 6)}


def viewer_frames(run: Path) -> dict[str, Any]:
  measured, frames = bench_viewer.bench_run(run, VIEWER_VIEWS)
  return {"seconds": measured["frames"][-1]["seconds_to_frame"], "frames": measured["frames"],
          "result": hashlib.sha256(np.asarray(frames[-1].rgb).tobytes()).hexdigest()[:16]}


def run_child(args: argparse.Namespace) -> dict[str, Any]:
  """Runs the workload `args.child` in this process (the allocator set as the environment says)
  and returns its measurements."""
  kept = allocator.keep_freed_memory()
  work: Callable[[], dict[str, Any]] = {
      "nerf_train": lambda: nerf_train(args.nerf_steps),
      "nerf_budget": lambda: nerf_budget(args.budget_seconds), "nerf_render": nerf_render,
      "unet_forward": unet_forward, "update": update,
      "nerf_eval": lambda: nerf_eval(args.run),
      "viewer_frames": lambda: viewer_frames(args.run)}[args.child]
  before = resource.getrusage(resource.RUSAGE_SELF)
  measured = work()
  after = resource.getrusage(resource.RUSAGE_SELF)
  return {**measured, "keeps_freed_memory": kept,
          "process_user_seconds": round(after.ru_utime - before.ru_utime, 2),
          "process_system_seconds": round(after.ru_stime - before.ru_stime, 2),
          "minor_page_faults": after.ru_minflt - before.ru_minflt,
          "peak_rss_bytes": after.ru_maxrss * 1024}


def measure_in_child(workload: str, mode: str, args: argparse.Namespace) -> dict[str, Any]:
  environment = {**os.environ, **MODES[mode]}
  completed = subprocess.run(
      [sys.executable, __file__, "--child", workload, "--nerf_steps", str(args.nerf_steps),
       "--budget_seconds", str(args.budget_seconds),
       *(["--run", str(args.run)] if args.run else [])],
      env=environment, capture_output=True, text=True, check=False)
  if completed.returncode:
    raise RuntimeError(f"{workload} ({mode}) failed:\n{completed.stderr[-3000:]}")
  return json.loads(completed.stdout.strip().splitlines()[-1])


def summarise(workload: str, runs: dict[str, list[dict[str, Any]]]) -> dict[str, Any]:
  """Medians per mode and each mode's median speed-up over glibc's defaults (`speedups`); for a
  fixed amount of work whether every run gave the same result, for a time budget (nerf_budget)
  the steps and PSNR reached."""
  fields = ("seconds", "process_system_seconds", "minor_page_faults", "peak_rss_bytes")
  if workload == "nerf_budget":
    fields += ("steps", "result")
  summary: dict[str, Any] = {mode: {field: statistics.median(run[field] for run in mode_runs)
                                    for field in fields} for mode, mode_runs in runs.items()}
  summary["speedup_over_glibc_default"] = {
      mode: round(statistics.median(speedups(workload, runs, mode)), 3)
      for mode in runs if mode != "glibc_default"}
  if workload != "nerf_budget":
    summary["same_results"] = len({run["result"] for mode_runs in runs.values()
                                   for run in mode_runs}) == 1
  return summary


def speedups(workload: str, runs: dict[str, list[dict[str, Any]]], mode: str) -> list[float]:
  """Per round: how much faster `mode` was than glibc's defaults (default seconds over its
  seconds; for a time budget, its steps over default steps)."""
  pairs = zip(runs["glibc_default"], runs[mode])
  if workload == "nerf_budget":
    return [other["steps"] / default["steps"] for default, other in pairs]
  return [default["seconds"] / other["seconds"] for default, other in pairs]


def write_figure(path: Path, result: dict[str, Any]) -> None:
  """One row per workload and mode: the median speed-up, the line spanning the rounds'."""
  rows = []
  for workload, measured in result["workloads"].items():
    for mode in measured["runs"]:
      if mode != "glibc_default":
        ratios = speedups(workload, measured["runs"], mode)
        rows.append((f"{workload}, {mode}", statistics.median(ratios), min(ratios), max(ratios)))
  plotting.write_panels(path, [plotting.interval_chart(
      "allocator settings: speed-up", rows, "x glibc's default (1 = same)", width=620)])


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--workloads", nargs="+", choices=WORKLOADS,
                      default=list(DEFAULT_WORKLOADS))
  parser.add_argument("--modes", nargs="+", choices=list(MODES), default=list(MODES),
                      help="allocator settings to compare (glibc_default always runs)")
  parser.add_argument("--rounds", type=int, default=2, help="child runs per workload and mode")
  parser.add_argument("--nerf_steps", type=int, default=300, help="nerf_train's steps")
  parser.add_argument("--budget_seconds", type=float, default=300.0,
                      help="nerf_budget's training seconds")
  parser.add_argument("--run", type=Path, help="the trained run of nerf_eval and viewer_frames")
  parser.add_argument("--name", default="bench_allocator", help="results/<name>.json")
  parser.add_argument("--child", choices=WORKLOADS, help=argparse.SUPPRESS)
  results_dir.add_argument(parser)
  args = parser.parse_args()
  needing_run = set(RUN_WORKLOADS) & {*args.workloads, args.child}
  if needing_run and args.run is None:
    parser.error(f"{', '.join(sorted(needing_run))} need --run RUN (a `signerf train` directory)")
  if args.child:
    print(json.dumps(run_child(args)), flush=True)
    return
  modes = ["glibc_default", *(mode for mode in args.modes if mode != "glibc_default")]
  result: dict[str, Any] = {"machine": machine.record(), "rounds": args.rounds, "modes": modes,
                            "nerf_steps": args.nerf_steps,
                            "budget_seconds": args.budget_seconds, "workloads": {}}
  for workload in args.workloads:
    runs: dict[str, list[dict[str, Any]]] = {mode: [] for mode in modes}
    for _ in range(args.rounds):
      for mode in modes:
        runs[mode].append(measure_in_child(workload, mode, args))
        print(workload, mode, runs[mode][-1], flush=True)
    result["workloads"][workload] = {"runs": runs, "summary": summarise(workload, runs)}
    print(workload, result["workloads"][workload]["summary"], flush=True)
  result["machine"]["load_average_at_end"] = os.getloadavg()
  files.write_json(args.results / f"{args.name}.json", result)
  write_figure(args.results / f"{args.name}.png", result)
  print(f"bench_allocator: results in {args.results / args.name}.{{json,png}}")


if __name__ == "__main__":
  main()
