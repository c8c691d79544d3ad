"""Throughput of the image set update and of NeRF training against the device count, with the
results checked to agree across device counts; and the multi-host entry point.

    python experiments/scaling.py [--gin_file scaling] [--gin_param 'scaling.nerf_steps = 80']

runs one worker process per device count N in `scaling.device_counts`: on CPU with
XLA_FLAGS=--xla_force_host_platform_device_count=N (the same cores split into N devices, so this
measures what sharding costs and that it changes nothing, not more compute), on GPU/TPU hosts on
the first N accelerators. Each worker measures, after compilation:
  * the image set update (`editing.update.update_batch`: the batch sharded along "views",
    `views_per_device` per device) in views per second, with the shipped model if
    signerf_jax/default_model/weights exists, else the same architecture with freshly
    initialised weights (the JSON says which: throughput depends on the shapes only);
  * NeRF training (`nerf.train`: each step's rays split over the devices) on a generated
    synthetic scene, in steps and rays per second.
The driver then checks that every device count edits the same images and trains with the same
losses at every step (to the tolerances below; the parameters' largest difference is reported
too), and with `scaling.local_processes = P > 0`
runs the multi-host entry point as P processes on 127.0.0.1 (one CPU device each), checked the
same way. Writes scaling.json (with the machine, the code's commit, the gin settings and every
seed), scaling.gin and scaling.png into --results DIR (default outputs/experiments/).

Multi-host (one process per host; HOST:PORT is process 0's, reachable from every host):

    python experiments/scaling.py --coordinator_address HOST:PORT --num_processes P \\
        --process_id I [--gin_file scaling]

Every process joins `jax.distributed` and measures on the devices of all processes; process 0
writes scaling_multihost.json into --results DIR (or --output STEM.json). On one machine, start
the P commands in P shells (CPU: add XLA_FLAGS=--xla_force_host_platform_device_count=1
JAX_PLATFORMS=cpu).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Sequence

import gin
import jax
import jax.numpy as jnp
import numpy as np

from signerf_jax import configs, files, parallel
from signerf_jax.clip import word_tokenizer
from signerf_jax.data import synthetic, synthetic_render
from signerf_jax.default_model import export
from signerf_jax.default_model import model as model_lib
from signerf_jax.diffusion import pipeline as pipeline_lib
from signerf_jax.diffusion.attention import AttentionOptions
from signerf_jax.editing import crops, generation, update
from signerf_jax.editing import sheet as sheet_lib
from signerf_jax.editing.config import DEFAULT_MODEL_DIR
from signerf_jax.errors import InputError
from signerf_jax.geometry import control_depth
from signerf_jax.nerf import capacity as capacity_lib
from signerf_jax.nerf import train, training_run

import machine  # experiments/machine.py and plotting.py (this script's directory is on sys.path)
import plotting
import results_dir

SCRIPT = Path(__file__).resolve()


@gin.configurable("scaling")
@dataclasses.dataclass(frozen=True)
class ScalingConfig:
  """What the experiment measures.

  Attributes:
    device_counts: one worker per count; the first is the reference of the comparisons.
    local_processes: processes of the local multi-host demonstration (0: none).
    prompt: the edit prompt.
    views_per_device: views each device inpaints per batch.
    update_views: views edited per device count (a multiple of every batch keeps batches full).
    scene_seed: the synthetic scene (its size: `synthetic_cameras.*`, `synthetic_scene.*`).
    nerf_warmup_steps: untimed steps first (compilation, the first occupancy refresh).
    nerf_steps: timed steps after them; losses of all steps are compared.
    image_tolerance: max |difference| of edited images (in [0, 1]) counted as identical.
    loss_tolerance: max relative difference of NeRF losses counted as identical.
    worker_timeout_seconds: a worker taking longer is stopped and reported.
  """

  device_counts: tuple[int, ...] = (1, 2, 4)
  local_processes: int = 2
  prompt: str = "a red cow"
  views_per_device: int = 2
  update_views: int = 8
  scene_seed: int = 0
  nerf_warmup_steps: int = 4
  nerf_steps: int = 40
  image_tolerance: float = 1e-4
  loss_tolerance: float = 1e-4
  worker_timeout_seconds: float = 600.0


@dataclasses.dataclass(frozen=True)
class LibrarySettings:
  """The library's settings a worker uses, built from the gin bindings (`from_gin`).

  Attributes:
    scene, cameras: the synthetic scene (`synthetic_scene.*`, `synthetic_cameras.*`).
    generation, attention: the image set update's diffusion settings.
    training, capacity: the NeRF's training settings and how its size is derived.
  """

  scene: synthetic.SceneSettings
  cameras: synthetic_render.CameraRig
  generation: pipeline_lib.GenerationOptions
  attention: AttentionOptions
  training: train.TrainConfig
  capacity: capacity_lib.CapacityRules

  @classmethod
  def from_gin(cls) -> "LibrarySettings":
    return cls(configs.build(synthetic.SceneSettings), configs.build(synthetic_render.CameraRig),
               configs.build(pipeline_lib.GenerationOptions), configs.build(AttentionOptions),
               configs.build(train.TrainConfig), configs.build(capacity_lib.CapacityRules))


# ------------------------------------------------------------------------------------------------
# The worker: measurements on the devices it sees.


def diffusion_model(directory: Path, prompt: str) -> tuple[str, str]:
  """(model directory, "shipped" or "random"): the shipped model if present, else a checkpoint
  of the same architecture (gin: `default_model_architecture.*`) with freshly initialised
  weights, written to `directory`."""
  if (DEFAULT_MODEL_DIR / "model_index.json").is_file():
    return str(DEFAULT_MODEL_DIR), "shipped"
  architecture = model_lib.Architecture()
  tokenizer = word_tokenizer.WordTokenizer.from_words([prompt],
                                                      architecture.max_text_length)
  components = model_lib.build(architecture, tokenizer.vocab_size)
  rng = np.random.default_rng(0)
  unet = model_lib.init_unet(components, rng)
  params = {"vae": model_lib.init_vae(components, rng), "unet": unet,
            "controlnet": model_lib.init_controlnet(components, unet, rng),
            "text_encoder": model_lib.init_text_encoder(components, rng)}
  export.write_checkpoint(directory, architecture, params, tokenizer, dtype=np.float32)
  return str(directory), "random"


def update_inputs(dataset, layout: sheet_lib.SheetLayout, count: int):
  """The first `count` views with a centred disc mask, and a reference sheet whose tiles are the
  views after them (full frames)."""
  boxes = np.asarray(update.tile_boxes(dataset.cameras, layout))
  controls = np.asarray(control_depth.normalize_control_depth(dataset.depths, dataset.near,
                                                              dataset.far))
  rows, columns = np.mgrid[:dataset.height, :dataset.width] + 0.5
  radius = 0.3 * min(dataset.height, dataset.width)
  disc = np.hypot(rows - dataset.height / 2, columns - dataset.width / 2) < radius
  masks = np.broadcast_to(disc, (dataset.num_images,) + disc.shape).astype(np.float32)
  views = update.SlotViews(dataset.images[:count], masks[:count], controls[:count],
                           boxes[:count])
  reference = np.arange(count, count + layout.num_tiles)
  if reference[-1] >= dataset.num_images:
    raise InputError(f"the update needs {reference[-1] + 1} views of the scene, it has "
                     f"{dataset.num_images}: lower it or raise synthetic_cameras.num_views",
                     field="scaling.update_views")
  tiles = lambda array, fill: crops.crop_to_tiles(jnp.asarray(array[reference], jnp.float32),
                                                  jnp.asarray(boxes[reference]),
                                                  layout.tile_height, layout.tile_width, fill)
  empty = lambda channels: jnp.zeros((layout.tile_height, layout.tile_width, channels))
  sheet_rgb = sheet_lib.assemble(tiles(dataset.images, update.TILE_FILL_COLOR), empty(3), layout)
  sheet_control = sheet_lib.assemble(tiles(controls[..., None], 0.0), empty(1), layout)
  return views, np.asarray(sheet_rgb), np.asarray(sheet_control)


def measure_update(config: ScalingConfig, library: LibrarySettings, model: str, dataset,
                   devices) -> tuple[dict, np.ndarray]:
  """Views per second of the sharded image set update, and the edited views."""
  started = time.perf_counter()
  generator = generation.load_generator(model, "", "", config.prompt, "", library.generation,
                                        config.views_per_device, attention=library.attention,
                                        mesh=parallel.device_mesh(devices, generation.MESH_AXIS))
  tile = generation.native_tile_size(model)
  layout = sheet_lib.SheetLayout(tile_height=tile, tile_width=tile)
  views, sheet_rgb, sheet_control = update_inputs(dataset, layout, config.update_views)
  load_seconds = time.perf_counter() - started
  batches = [np.arange(start, min(start + generator.batch_size, config.update_views))
             for start in range(0, config.update_views, generator.batch_size)]

  def edit(batch):
    keys = np.stack([generation.view_key(0, int(index)) for index in batch])
    chosen = update.SlotViews(*(array[batch] for array in dataclasses.astuple(views)))
    return update.update_batch(generator, sheet_rgb, sheet_control, layout, chosen, keys)[0]

  started = time.perf_counter()
  edit(batches[0])  # Compiles.
  compile_seconds = time.perf_counter() - started
  started = time.perf_counter()
  edited = np.concatenate([edit(batch) for batch in batches])
  seconds = time.perf_counter() - started
  return {"views": config.update_views, "batch_size": generator.batch_size,
          "views_per_device": config.views_per_device, "tile_size": tile,
          "load_seconds": load_seconds, "compile_seconds": compile_seconds,
          "seconds": seconds, "views_per_second": config.update_views / seconds}, edited


def measure_nerf(config: ScalingConfig, library: LibrarySettings, dataset, devices
                 ) -> tuple[dict, dict[str, np.ndarray]]:
  """Steps and rays per second of data-parallel training; the losses and final parameters."""
  model = training_run.build_model(dataset, rules=library.capacity)
  run_config = dataclasses.replace(library.training,
                                   steps=config.nerf_warmup_steps + config.nerf_steps)
  trainer = training_run.make_trainer(dataset, model=model, config=run_config,
                                      mesh=parallel.device_mesh(devices))
  losses = []
  started = time.perf_counter()
  for step in range(1, config.nerf_warmup_steps + 1):
    losses.append(trainer.run(until_step=step, progress=False)["loss"])
  warmup_seconds = time.perf_counter() - started
  started = time.perf_counter()
  for step in range(config.nerf_warmup_steps + 1, run_config.steps + 1):
    losses.append(trainer.run(until_step=step, progress=False)["loss"])
  seconds = time.perf_counter() - started
  steps_per_second = config.nerf_steps / seconds
  parameters = jax.device_get(trainer.state.variables["params"])
  arrays = {f"parameter_{index}": np.asarray(leaf)
            for index, leaf in enumerate(jax.tree.leaves(parameters))}
  return {"rays_per_batch": model.capacity.rays_per_batch,
          "samples_per_batch": model.capacity.samples_per_batch,
          "sample_groups": model.capacity.sample_groups, "steps": config.nerf_steps,
          "warmup_steps": config.nerf_warmup_steps, "warmup_seconds": warmup_seconds,
          "seconds": seconds, "steps_per_second": steps_per_second,
          "rays_per_second": steps_per_second * model.capacity.rays_per_batch,
          "final_loss": losses[-1]}, {"losses": np.asarray(losses), **arrays}


def run_worker(config: ScalingConfig, library: LibrarySettings, devices: Sequence, output: Path
               ) -> None:
  """Measures on `devices`; writes output.json and output.npz (process 0 only)."""
  with tempfile.TemporaryDirectory() as workdir:
    dataset, _ = synthetic_render.generate(Path(workdir) / "scene", seed=config.scene_seed,
                                           settings=library.scene, rig=library.cameras)
    model, model_kind = diffusion_model(Path(workdir) / "random_model", config.prompt)
    result: dict[str, Any] = {
        "devices": len(devices), "processes": jax.process_count(),
        "platform": jax.default_backend(), "model_weights": model_kind,
        "model": model if model_kind == "shipped" else "the default model's architecture "
                 "(default_model_architecture.*), freshly initialised weights",
        "scene": {"views": dataset.num_images, "image_size": [dataset.width, dataset.height]}}
    arrays: dict[str, np.ndarray] = {}
    try:
      result["update"], arrays["edited"] = measure_update(config, library, model, dataset,
                                                          devices)
    except Exception as error:  # pylint: disable=broad-except
      # Recorded, not raised: the NeRF measurement still runs and the driver reports it.
      result["update"] = {"error": f"{type(error).__name__}: {error}"}
  result["nerf"], nerf_arrays = measure_nerf(config, library, dataset, devices)
  arrays.update({f"nerf_{name}": value for name, value in nerf_arrays.items()})
  if jax.process_index() == 0:
    with files.atomic_path(output.with_suffix(".npz")) as temporary:
      np.savez(temporary, **arrays)
    files.write_json(output.with_suffix(".json"), result)


# ------------------------------------------------------------------------------------------------
# The driver: one worker per device count, comparisons, plot.


def _gin_arguments(args) -> list[str]:
  return ([f"--gin_file={name}" for name in args.gin_file]
          + [f"--gin_param={binding}" for binding in args.gin_param])


def _cpu_environment(devices: int) -> dict[str, str]:
  return dict(os.environ, JAX_PLATFORMS="cpu",
              XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}")


def run_workers(commands: Sequence[list[str]], environment: dict[str, str], timeout: float
                ) -> list[dict[str, Any]]:
  """Runs the commands at once (the processes of one run) and reports how each ended."""
  processes = [subprocess.Popen(command, env=environment, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True) for command in commands]
  reports = []
  for process in processes:
    try:
      output, _ = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
      process.kill()
      output, _ = process.communicate()
      output += f"\n(stopped after {timeout:.0f} s)"
    reports.append({"returncode": process.returncode, "log_tail": output[-3000:]})
  return reports


def _free_port() -> int:
  with socket.socket() as probe:
    probe.bind(("127.0.0.1", 0))
    return probe.getsockname()[1]


def compare(reference: dict, other: dict, config: ScalingConfig) -> dict[str, Any]:
  """Largest differences between two workers' outputs, and whether they are within tolerance."""
  differences: dict[str, Any] = {}
  if "edited" in reference and "edited" in other:
    differences["edited_images_max_abs"] = float(np.max(np.abs(other["edited"]
                                                                - reference["edited"])))
  losses = reference["nerf_losses"], other["nerf_losses"]
  differences["nerf_losses_max_relative"] = float(np.max(np.abs(losses[1] - losses[0])
                                                          / np.abs(losses[0])))
  differences["nerf_final_loss"] = [float(losses[0][-1]), float(losses[1][-1])]
  names = [name for name in reference if name.startswith("nerf_parameter_")]
  # Not a criterion: Adam (eps 1e-15) scales each parameter's gradient to about +-1, so a
  # near-zero gradient whose rounding depends on the order of the sums moves a parameter by up
  # to the learning rate, and such differences grow over steps while the loss stays the same.
  differences["nerf_parameters_max_abs"] = max(
      float(np.max(np.abs(other[name] - reference[name]))) for name in names)
  differences["identical_to_tolerance"] = bool(
      differences.get("edited_images_max_abs", 0.0) <= config.image_tolerance
      and differences["nerf_losses_max_relative"] <= config.loss_tolerance)
  if "edited_images_max_abs" not in differences:
    differences["identical_to_tolerance_note"] = "NeRF only: no update result to compare"
  return differences


def _read_worker(output: Path) -> tuple[dict, dict] | None:
  if not output.with_suffix(".json").is_file():
    return None
  return (json.loads(output.with_suffix(".json").read_text()),
          dict(np.load(output.with_suffix(".npz"))))


def probe_devices() -> tuple[str, int]:
  """(backend, device count) of this host, asked in a child process: the driver itself never
  starts a JAX backend (on accelerators it would hold memory the workers need)."""
  probe = subprocess.run([sys.executable, "-c", "import jax; print(jax.default_backend(), "
                          "jax.device_count())"], capture_output=True, text=True, check=True)
  backend, count = probe.stdout.split()[-2:]
  return backend, int(count)


def run_driver(config: ScalingConfig, args) -> dict[str, Any]:
  backend, available = probe_devices()
  result: dict[str, Any] = {
      "machine": machine.record(backend=backend), "config": dataclasses.asdict(config),
      **machine.settings_record(gin.config_str(), scaling=config,
                                library=LibrarySettings.from_gin()),
      "device_counts": {}}
  if backend == "cpu":
    result["note"] = (f"CPU: N devices are the same {os.cpu_count()} cores split by "
                      "--xla_force_host_platform_device_count=N, so throughput cannot grow "
                      "with N; the ratios show what sharding costs (or gains from running "
                      "single-threaded XLA work side by side), the comparisons that it changes "
                      "no result.")
  with tempfile.TemporaryDirectory() as workdir:
    workdir = Path(workdir)
    worker = [sys.executable, str(SCRIPT), *_gin_arguments(args)]
    outputs: dict[str, tuple[dict, dict]] = {}
    for count in config.device_counts:
      if backend != "cpu" and count > available:
        result["device_counts"][str(count)] = {"skipped": f"only {available} devices"}
        continue
      environment = _cpu_environment(count) if backend == "cpu" else dict(os.environ)
      output = workdir / f"devices_{count}"
      print(f"scaling: {count} device(s)", flush=True)
      report, = run_workers([worker + ["--devices", str(count), "--output", str(output)]],
                            environment, config.worker_timeout_seconds)
      read = _read_worker(output)
      if read is None:
        result["device_counts"][str(count)] = {"failed": report}
        continue
      outputs[str(count)] = read
      result["device_counts"][str(count)] = read[0]
    if config.local_processes > 0:
      address = f"127.0.0.1:{_free_port()}"
      output = workdir / "multihost"
      print(f"scaling: {config.local_processes} processes through {address}", flush=True)
      commands = [worker + ["--coordinator_address", address, "--num_processes",
                            str(config.local_processes), "--process_id", str(index),
                            "--output", str(output)]
                  for index in range(config.local_processes)]
      reports = run_workers(commands, _cpu_environment(1), config.worker_timeout_seconds)
      read = _read_worker(output)
      result["multihost"] = {"processes": config.local_processes,
                             "coordinator_address": address, "devices_per_process": 1}
      if read is None:
        result["multihost"]["failed"] = reports
      else:
        outputs["multihost"] = read
        result["multihost"].update(read[0])
  reference = next(iter(outputs), None)
  result["model_weights"] = outputs[reference][0]["model_weights"] if outputs else None
  result["comparisons"] = {
      f"{name} vs {reference}": compare(outputs[reference][1], outputs[name][1], config)
      for name in outputs if name != reference}
  result["identical_to_tolerance"] = all(comparison["identical_to_tolerance"]
                                         for comparison in result["comparisons"].values())
  result["speedups"] = speedups(result)
  result["load_average_at_end"] = os.getloadavg()
  return result


def speedups(result: dict[str, Any]) -> dict[str, dict[str, float]]:
  """Throughput of each device count over the first one's (measured in the same run)."""
  measured = {int(count): entry for count, entry in result["device_counts"].items()
              if "nerf" in entry}
  if not measured:
    return {}
  first = measured[min(measured)]
  ratios: dict[str, dict[str, float]] = {"nerf_rays_per_second": {}, "update_views_per_second": {}}
  for count, entry in sorted(measured.items()):
    ratios["nerf_rays_per_second"][str(count)] = (entry["nerf"]["rays_per_second"]
                                                  / first["nerf"]["rays_per_second"])
    if "views_per_second" in entry["update"] and "views_per_second" in first["update"]:
      ratios["update_views_per_second"][str(count)] = (entry["update"]["views_per_second"]
                                                       / first["update"]["views_per_second"])
  return ratios


def plot(result: dict[str, Any], path: Path) -> None:
  """Throughput against device count, measured and ideal (linear from one device), per part;
  the multi-host run as a separate point."""
  measured = {int(count): entry for count, entry in result["device_counts"].items()
              if "nerf" in entry}
  counts = sorted(measured)
  panels = []
  for title, part, key, label in (
      (f"image set update ({result['model_weights']} weights)", "update", "views_per_second",
       "views / s"),
      ("NeRF training", "nerf", "rays_per_second", "rays / s")):
    points = [(count, measured[count][part][key]) for count in counts
              if key in measured[count][part]]
    if not points:
      continue
    x, y = zip(*points)
    series = [plotting.Series("one process", x, y),
              plotting.Series("linear", x, [y[0] * count / x[0] for count in x], dashed=True)]
    multihost = result.get("multihost", {})
    if key in multihost.get(part, {}):
      series.append(plotting.Series(f"{multihost['processes']} processes (jax.distributed)",
                                    [multihost["devices"]], [multihost[part][key]]))
    panels.append(plotting.line_chart(title, series, x_label="devices", y_label=label,
                                      x_ticks=x))
  plotting.write_panels(path, panels)


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  configs.add_gin_arguments(parser)
  parser.add_argument("--coordinator_address", help="HOST:PORT of process 0 (multi-host)")
  parser.add_argument("--num_processes", type=int, default=1)
  parser.add_argument("--process_id", type=int, default=0)
  results_dir.add_argument(parser)
  parser.add_argument("--output", help="worker output path stem (.json, .npz); default: "
                      "DIR/scaling_multihost with --coordinator_address")
  parser.add_argument("--devices", type=int, help=argparse.SUPPRESS)  # Set for workers.
  args = parser.parse_args(argv)
  args.gin_file = args.gin_file or ["scaling"]
  if args.coordinator_address:
    parallel.initialize_distributed(args.coordinator_address, args.num_processes,
                                    args.process_id)
  configs.parse_gin(args.gin_file, args.gin_param)
  config = ScalingConfig()
  if args.coordinator_address or args.devices:
    output = Path(args.output or args.results / "scaling_multihost")
    run_worker(config, LibrarySettings.from_gin(),
               jax.devices()[:args.devices] if args.devices else jax.devices(), output)
    if not args.devices and jax.process_index() == 0:
      files.write_text(output.with_suffix(".gin"), gin.config_str())
      print(f"scaling: multi-host results in {output}.json")
    return 0
  result = run_driver(config, args)
  output = args.results / "scaling.json"
  files.write_json(output, result)
  files.write_text(output.with_suffix(".gin"), gin.config_str())
  plot(result, output.with_suffix(".png"))
  print(f"scaling: {json.dumps(result['speedups'])}; identical to tolerance: "
        f"{result['identical_to_tolerance']}; results in {output}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
