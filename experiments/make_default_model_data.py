"""Generates the default model's procedural data and reports its speed, size and sanity checks.

    python experiments/make_default_model_data.py --out DIR [--workers N] \
        [--gin_file default_model_data] [--gin_param 'default_model_data.num_sheets = 400' ...]

Makes (or resumes) the dataset in DIR (`signerf_jax.default_model.dataset_builder`), then writes
default_model_data.json (and .gin, the full configuration) into --results DIR (default
outputs/experiments/), or --output JSON:
  * per kind: samples per second in one process (from the time spent making each shard, so a
    resumed run still reports it), bytes per sample, and the size and one-process time
    extrapolated to 4,000 sheets + 8,000 single views (the issue's example);
  * the ground-truth check of the prompt-adherence gate: the share of the objects in the eval
    split whose dominant colour (`colors.dominant_color`, what the gate applies to
    generated images) is their colour label; the gate (>= 0.9) is only meaningful if the
    renders themselves pass it by a margin;
  * how much of the frame the object covers: its silhouette's bounding box as a fraction of the
    frame, for reference and dataset views (percentiles 10, 50, 90).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

import gin
import numpy as np

from signerf_jax import configs, files
from signerf_jax.default_model import dataset_builder, samples
from signerf_jax.metrics import colors

import machine  # experiments/machine.py (this script's directory is on sys.path)
import results_dir  # experiments/results_dir.py (this script's directory is on sys.path)

EXTRAPOLATE_TO = {"sheets": 4000, "singles": 8000}


def _shards(directory: str, split: str, kind: str):
  for path in dataset_builder.shard_paths(directory, split, kind):
    yield dataset_builder.read_shard(path)


def color_check(directory: str) -> dict:
  """Share of eval views whose object's dominant colour is its label, per kind."""
  result = {}
  for kind in dataset_builder.KINDS:
    hits, total, confusions = 0, 0, {}
    for shard in _shards(directory, "eval", kind):
      for rgb, silhouette, label in zip(shard["rgb"], shard["silhouette"], shard["color"]):
        for view_rgb, view_silhouette in zip(rgb, silhouette):
          found = colors.dominant_color(view_rgb[view_silhouette > 0] / 255.0)
          hits += found == label
          total += 1
          if found != label:
            key = f"{label}->{found}"
            confusions[key] = confusions.get(key, 0) + 1
    result[kind] = {"views": total, "accuracy": hits / total if total else None,
                    "confusions": confusions}
  return result


def frame_coverage(directory: str) -> dict:
  """Percentiles (10, 50, 90) of the object's bounding-box area over the frame, by view kind."""
  fractions = {name: [] for name in samples.VIEW_KINDS}
  for kind in dataset_builder.KINDS:
    for shard in _shards(directory, "train", kind):
      size = shard["rgb"].shape[-2]
      boxes = shard["boxes"].reshape(-1, 4).astype(np.float64)
      area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1]) / size**2
      view_kinds = shard["view_kinds"].reshape(-1)
      for index, name in enumerate(samples.VIEW_KINDS):
        fractions[name].extend(area[view_kinds == index])
  return {name: {"views": len(values), "percentiles_10_50_90":
                 np.percentile(values, [10, 50, 90]).tolist() if values else None}
          for name, values in fractions.items()}


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--out", help="dataset directory (else default_model_data.output_directory)")
  parser.add_argument("--workers", type=int, default=1, help="processes making shards")
  configs.add_gin_arguments(parser)
  results_dir.add_argument(parser)
  parser.add_argument("--output", metavar="JSON",
                      help="the json to write (default: DIR/default_model_data.json)")
  args = parser.parse_args(argv)
  configs.parse_gin(args.gin_file or ["default_model_data"], args.gin_param)
  settings = dataset_builder.DataSettings()
  if args.out:
    settings = dataclasses.replace(settings, output_directory=args.out)
  start = time.perf_counter()
  manifest = dataset_builder.build_dataset(settings, workers=args.workers)
  wall_seconds = time.perf_counter() - start
  directory = settings.output_directory

  per_kind = {}
  for kind in dataset_builder.KINDS:
    train = manifest["splits"]["train"][kind]
    rate = train["samples_per_second"]
    bytes_per_sample = train["bytes"] / max(train["samples"], 1)
    per_kind[kind] = {
        "train_samples": train["samples"], "samples_per_second_one_process": rate,
        "bytes_per_sample": bytes_per_sample,
        f"extrapolated_to_{EXTRAPOLATE_TO[kind]}": {
            "bytes": bytes_per_sample * EXTRAPOLATE_TO[kind],
            "seconds_one_process": EXTRAPOLATE_TO[kind] / rate if rate else None},
    }
  results = {
      "dataset": directory, "fingerprint": manifest["fingerprint"], "workers": args.workers,
      "wall_seconds_this_run": wall_seconds, "dataset_bytes": manifest["bytes"],
      "catalogue": [entry["kind"] for entry in manifest["catalogue"]],
      "per_kind": per_kind,
      "extrapolated_total": {
          "samples": EXTRAPOLATE_TO,
          "bytes": sum(per_kind[kind][f"extrapolated_to_{count}"]["bytes"]
                       for kind, count in EXTRAPOLATE_TO.items()),
          "seconds_one_process": sum(per_kind[kind][f"extrapolated_to_{count}"][
              "seconds_one_process"] or 0.0 for kind, count in EXTRAPOLATE_TO.items())},
      "ground_truth_dominant_color": color_check(directory),
      "object_frame_coverage": frame_coverage(directory),
      "machine": {"cpu_count": os.cpu_count(), "shared_with_other_jobs": True,
                  "load_average_after": os.getloadavg()[0], **machine.code_version()},
      "gin_config": gin.config_str(),
  }
  output = Path(args.output or args.results / "default_model_data.json")
  files.write_json(output, results)
  files.write_text(output.with_suffix(".gin"), gin.config_str())
  print(f"wrote {output}: {manifest['bytes'] / 1e6:.1f} MB in {directory}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
