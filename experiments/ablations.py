"""Ablations of the edit on the demo's synthetic scene: quality against wall time.

    python experiments/ablations.py [--only NAME] [--smoke] [--model DIR] [--out DIR]
        [--results DIR] [--gin_file F] [--gin_param P]

The baseline is `signerf demo`'s edit (gin_configs/demo.gin: a cow proxy stood on the scene's
free spot, "a red cow", the shipped model) with gin_configs/ablations.gin on top; each ablation
changes one thing of it (values: `ablations.*` in that file):

  controlnet_scale  the first iteration's ControlNet conditioning scale;
  proxy             the proxy's fidelity: the spot cow (5856 triangles), spot's Catmull-Clark
                    control cage (low poly, 372 triangles) and the primitive cow (a box, four
                    cylinders and a sphere) -- spot from ../shared/data/meshes when present;
  sheet_layout      rows x columns of the sheet, i.e. rows * columns - 1 reference cameras;
  propagation       sheet propagation against independent per-view generation: the baseline's
                    evaluation edits some views on their own too (same prompt, seed, settings)
                    and compares verified correspondences (no extra run);
  crops             whole downscaled frames as tiles against crops around the selection;
  nerf_update       the NeRF update: fine-tuned or retrained, inside the edit region only
                    (`FinetuneConfig.edit_region`) or as a whole, as the paper does.

The synthetic scene (OUT/scene) and the original NeRF (OUT/original) are made once; every
variant is an edit run in OUT/ABLATION/VARIANT reusing that NeRF, and variants that are the same
edit (e.g. the baseline, listed by several ablations) run once
(`editing.commands.sweeps`). Reruns resume.
Quality comes from each edit's evaluation (background PSNR, consistency, prompt colour, proxy
shape IoU, and the edited NeRF's fit and solidity: `sweeps.edit_quality`), time is the edit's
stages' wall time without the shared NeRF and the evaluation.

The NeRFs train for step counts (gin_configs/ablations.gin), not seconds, so that the result
does not depend on the machine's speed: a rerun gives the same numbers, only the seconds differ
(tests/editing/test_ablation_reproducible.py).

Writes into --results DIR (default outputs/experiments/) ablations.json (the machine and the
code's commit, the common gin settings and every seed, each variant's bindings, quality and
stage seconds), ablations.gin (the common settings) and ablations.png (one row per ablation:
each quality number against seconds, one point per variant). --smoke adds
gin_configs/ablations_smoke.gin: few steps, a few minutes, meaningless numbers.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import gin
import numpy as np

from signerf_jax import configs, files
from signerf_jax.data import synthetic
from signerf_jax.editing import commands, demo
from signerf_jax.editing.commands import sweeps
from signerf_jax.editing.config import PRIMITIVE_PREFIX
from signerf_jax.editing.commands.sweeps import Variant
from signerf_jax.errors import InputError

sys.path.insert(0, str(Path(__file__).resolve().parent))
import machine  # pylint: disable=wrong-import-position
import plotting  # pylint: disable=wrong-import-position
import results_dir  # pylint: disable=wrong-import-position

# Proxy names of `ablations.proxies` (anything else is a mesh file or primitive:NAME).
SPOT_DIRECTORY = Path(synthetic.DEFAULT_MESH_DIRECTORY) / "spot"
PROXY_MESHES = {"spot_high_poly": SPOT_DIRECTORY / "spot_triangulated.obj",
                "spot_low_poly": SPOT_DIRECTORY / "spot_control_mesh.obj"}
CONTROLNET_SCALE = "first_iteration/GenerationOptions.controlnet_conditioning_scale"
# (metrics key, panel title, y label) of the quality numbers drawn against time.
QUALITY_PANELS = (("background_psnr", "background PSNR", "dB"),
                  ("consistency_change", "consistency vs original", "rel. change"),
                  ("prompt_color_share", "prompt colour", "share of views"),
                  ("shape_iou", "proxy shape", "IoU"),
                  ("solidity_iou", "solidity (held out)", "IoU"),
                  ("solidity_opacity", "opacity in silhouette", "mean alpha"))
PANEL_WIDTH, PANEL_HEIGHT = 460, 340


@gin.configurable("ablations")
@dataclasses.dataclass(frozen=True)
class AblationConfig:
  """The values each ablation tries (gin: `ablations.<field>`).

  Attributes:
    controlnet_scales: first-iteration ControlNet conditioning scales (paper: 0.4 - 1.0).
    proxies: "spot_high_poly", "spot_low_poly", a mesh file or primitive:NAME.
    sheet_layouts: (rows, columns) of the sheet.
    crops: SheetConfig.crops values.
    nerf_updates: EditConfig.nerf_update values ("finetune", "retrain").
    edit_regions: FinetuneConfig.edit_region values.
  """

  controlnet_scales: tuple[float, ...] = (0.0, 0.4, 0.7, 1.0)
  proxies: tuple[str, ...] = ("spot_high_poly", "spot_low_poly", "primitive:cow")
  sheet_layouts: tuple[tuple[int, int], ...] = ((2, 2), (2, 3), (3, 3))
  crops: tuple[bool, ...] = (False, True)
  nerf_updates: tuple[str, ...] = ("finetune", "retrain")
  edit_regions: tuple[bool, ...] = (True, False)


@dataclasses.dataclass(frozen=True)
class Ablation:
  """What an ablation varies, its variants in run order, and those left out (a missing mesh)."""

  description: str
  variants: list[Variant]
  skipped: list[dict[str, str]] = dataclasses.field(default_factory=list)


def _proxy_ablation(proxies: tuple[str, ...]) -> Ablation:
  ablation = Ablation("proxy fidelity: high-poly spot, its low-poly control cage, primitive cow",
                      [])
  for name in proxies:
    source = str(PROXY_MESHES.get(name, name))
    if name in PROXY_MESHES:
      label = name
    elif name.startswith(PRIMITIVE_PREFIX):
      label = "primitive_" + name[len(PRIMITIVE_PREFIX):]
    else:
      label = Path(name).stem
    if not source.startswith(PRIMITIVE_PREFIX) and not Path(source).is_file():
      ablation.skipped.append({"name": label, "missing": source})
    else:
      ablation.variants.append(Variant(label, (f"SelectionConfig.proxy = {source!r}",)))
  return ablation


def ablations(config: AblationConfig) -> dict[str, Ablation]:
  """Every ablation by name, in run order."""
  return {
      "controlnet_scale": Ablation("ControlNet conditioning scale of the sheet and the update", [
          Variant(f"scale_{scale:g}", (f"{CONTROLNET_SCALE} = {float(scale)!r}",))
          for scale in config.controlnet_scales]),
      "proxy": _proxy_ablation(config.proxies),
      "sheet_layout": Ablation("sheet layout rows x columns (rows * columns - 1 reference "
                               "cameras)", [
          Variant(f"{rows}x{columns}", (f"SheetConfig.rows = {rows}",
                                        f"SheetConfig.columns = {columns}"))
          for rows, columns in config.sheet_layouts]),
      "propagation": Ablation("sheet propagation against independent per-view edits (the "
                              "baseline's evaluation)", [Variant("baseline")]),
      "crops": Ablation("tiles: whole downscaled frames against crops around the selection", [
          Variant("crops" if crops else "full_frames", (f"SheetConfig.crops = {bool(crops)}",))
          for crops in config.crops]),
      "nerf_update": Ablation("NeRF update: fine-tuned or retrained, inside the edit region "
                              "only or as a whole", [
          Variant(f"{update}_{'region' if region else 'whole'}",
                  (f"EditConfig.nerf_update = {update!r}",
                   f"FinetuneConfig.edit_region = {bool(region)}"))
          for update in config.nerf_updates for region in config.edit_regions]),
  }


def propagation_points(summary: dict[str, Any]) -> list[dict[str, Any]]:
  """The baseline's sheet-propagated and independent edits: consistency change against seconds
  per edited view."""
  quality, seconds = summary["quality"], summary["seconds_per_view"]
  return [{"name": "sheet_propagated", "seconds_per_view": seconds["sheet_propagated"],
           "consistency_change": quality["consistency_change"]},
          {"name": "independent", "seconds_per_view": seconds["independent"],
           "consistency_change": quality["independent_consistency_change"]}]


# ------------------------------------------------------------------------------------------------
# The figure.


def _note_panel(title: str, lines: list[str]) -> np.ndarray:
  """A blank panel with text, where a chart would have no extent (one point, or equal values)."""
  canvas = np.full((PANEL_HEIGHT, PANEL_WIDTH, 3), 255, np.uint8)
  for index, line in enumerate([title] + lines):
    cv2.putText(canvas, line, (10, 18 + 20 * index), plotting.FONT, 0.45, plotting.BLACK, 1,
                cv2.LINE_AA)
  return canvas


def scatter_panel(title: str, points: list[tuple[str, float | None, float | None]],
                  x_label: str, y_label: str) -> np.ndarray:
  """One labelled point per (label, x, y); points with an unknown coordinate are left out."""
  known = [(label, x, y) for label, x, y in points if x is not None and y is not None]
  xs, ys = np.asarray([x for _, x, _ in known]), np.asarray([y for _, _, y in known])
  if len(known) < 2 or np.ptp(xs) == 0 or np.ptp(ys) == 0:
    return _note_panel(title, [f"{label}: {y:.3g} at {x:.0f} s" for label, x, y in known]
                       or ["not measured"])
  return plotting.line_chart(title, [plotting.Series(label, [x], [y]) for label, x, y in known],
                             x_label=x_label, y_label=y_label, width=PANEL_WIDTH,
                             height=PANEL_HEIGHT, y_from_zero=False)


def ablation_figure(results: dict[str, Any]) -> np.ndarray:
  """[H, W, 3] uint8 BGR: one row of panels per ablation."""
  rows = []
  for name, result in results.items():
    if name == "propagation":
      rows.append([scatter_panel(f"{name}: consistency vs original", [
          (point["name"], point["seconds_per_view"], point["consistency_change"])
          for point in result["points"]], "seconds per edited view", "rel. change")])
      continue
    rows.append([scatter_panel(f"{name}: {title}", [
        (variant["name"], variant["edit_seconds"], variant["quality"][metric])
        for variant in result["variants"]], "edit seconds", y_label)
                 for metric, title, y_label in QUALITY_PANELS])
  width = max(len(row) for row in rows) * PANEL_WIDTH
  return np.concatenate([np.pad(np.concatenate(row, axis=1),
                                ((0, 0), (0, width - len(row) * PANEL_WIDTH), (0, 0)),
                                constant_values=255) for row in rows])


# ------------------------------------------------------------------------------------------------
# The experiment.


def run_ablations(names: list[str], gin_files: list[str], gin_params: list[str], out: Path,
                  model: str | None, progress: bool) -> tuple[dict[str, Any], str]:
  """Runs the chosen ablations; returns the results and the common gin settings."""
  log = lambda line: print(f"ablations: {line}", flush=True)
  configs.parse_gin(gin_files, gin_params)
  config, settings = AblationConfig(), configs.build(demo.DemoSettings)
  model = demo.model_directory(model)
  scene = demo.ensure_scene(out / "scene", settings.scene_seed)
  bindings = demo.edit_bindings(out / "scene", scene, settings, settings.prompt, model)
  sweep = sweeps.Sweep(out, gin_files, bindings + gin_params, progress, log)
  result: dict[str, Any] = {"machine": machine.record(), "gin_files": gin_files,
                            "model": model, "scene": str((out / "scene").resolve()),
                            "prompt": settings.prompt, "original_nerf": sweep.train_original(),
                            "ablations": {}}
  for name, ablation in ablations(config).items():
    if name not in names:
      continue
    for skipped in ablation.skipped:
      log(f"{name}/{skipped['name']}: skipped, {skipped['missing']} not found")
    entry: dict[str, Any] = {"description": ablation.description,
                             "variants": [sweep.run(name, variant)
                                          for variant in ablation.variants],
                             "skipped": ablation.skipped}
    if name == "propagation":
      entry["points"] = propagation_points(entry["variants"][0])
    result["ablations"][name] = entry
  configs.parse_gin(gin_files, sweep.bindings)
  # The common settings; each variant's bindings on top are in its entry.
  result.update(machine.settings_record(gin.config_str(), demo=settings,
                                        edit=commands.edit_settings()))
  return result, gin.config_str()


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  all_names = list(ablations(AblationConfig()))
  parser.add_argument("--only", action="append", choices=all_names,
                      help="run this ablation only (repeatable; default: all)")
  parser.add_argument("--smoke", action="store_true",
                      help="tiny budgets (gin_configs/ablations_smoke.gin): numbers meaningless")
  parser.add_argument("--model", help="diffusers ControlNet inpainting pipeline directory "
                      "(default: the shipped model)")
  parser.add_argument("--out", default="outputs/ablations", help="the edit runs (resumed)")
  results_dir.add_argument(parser)
  commands.add_common_arguments(parser)
  args = parser.parse_args(argv)
  start = time.perf_counter()
  gin_files = ["demo", "ablations", *(["ablations_smoke"] if args.smoke else []), *args.gin_file]
  names = args.only or all_names
  try:
    result, gin_config = run_ablations(names, gin_files, args.gin_param, Path(args.out),
                                       args.model, not args.quiet)
  except InputError as error:
    print(f"ablations: error: {error}", file=sys.stderr)
    return 2
  result["seconds"] = time.perf_counter() - start
  output = Path(args.results) / "ablations.json"
  files.write_json(output, result)
  files.write_text(output.with_suffix(".gin"), gin_config)
  plotting.write_panels(output.with_suffix(".png"), [ablation_figure(result["ablations"])])
  print(f"ablations: {', '.join(names)} in {result['seconds']:.0f} s -> {output}, "
        f"{output.with_suffix('.png')}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
