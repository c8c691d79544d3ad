"""Variants of one edit, for ablations: quality against wall time.

A `Sweep` holds common gin settings (files, then bindings). It trains the original NeRF once
(`train_original`) and every variant then reuses it (`EditConfig.original_run`), so a variant
costs only its edit. Each variant is an edit run in its own directory with its own bindings on
top; variants with the same pipeline key (`stages.edit_key`: every setting any stage reads)
are run once, whichever ablation lists them. JAX's compilation caches are cleared before
each run so that every variant pays for its own compilation, as a fresh `signerf edit` would.

`summarize_edit` reduces an edit to its headline quality numbers (`edit_quality`, from the
evaluation's metrics.json) and its wall time: the seconds of its stages except the shared
original NeRF and the evaluation (`SHARED_STAGES`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Callable, Sequence

import jax

from signerf_jax import configs, files
from signerf_jax.editing import commands, stages
from signerf_jax.editing.project import canonical_json

# Stages not counted in an edit's time: trained once for all variants, and measuring only.
SHARED_STAGES = ("original", "evaluate")
# Stages that make the sheet and propagate it (one preview candidate: the chosen sheet).
PROPAGATION_STAGES = ("preview", "sheet", "update")


@dataclasses.dataclass(frozen=True)
class Variant:
  """One edit of a sweep.

  Attributes:
    name: its label, and its directory's name inside the ablation's.
    bindings: gin bindings on top of the sweep's.
  """

  name: str
  bindings: tuple[str, ...] = ()


def _get(metrics: dict[str, Any], *path: str) -> Any:
  """metrics[path[0]][path[1]]..., or None where a level is missing or None."""
  value = metrics
  for name in path:
    if not isinstance(value, dict) or value.get(name) is None:
      return None
    value = value[name]
  return value


def edit_quality(metrics: dict[str, Any]) -> dict[str, float | None]:
  """The headline numbers of an edit's evaluation (metrics.json); None where not measured.

  Returns:
    background_psnr, background_ssim: the paper's PSNR_bg (dB) and SSIM_bg between original and
      edited NeRF renders outside the selection, at held-out cameras.
    consistency_change, independent_consistency_change: relative change, against the original
      images, of camera-verified SIFT correspondences (epipolar inliers) between neighbouring
      views, for the sheet-propagated edit and for independent per-view edits (-0.7: 70% fewer;
      the paper reports -15% and -70% with LoFTR).
    prompt_color_share: share of edited-NeRF renders whose selection shows the prompt's colour.
    shape_iou: IoU of the pixels the edit changed in edited-NeRF renders with the proxy's
      silhouette (proxy selections); edited_images_shape_iou: the same of the edited training
      images the NeRF was trained on (how closely the diffusion model followed the proxy).
    fit_psnr, solidity_iou, solidity_opacity: the edited NeRF's 3D consistency (issue 19,
      proxy selections): its PSNR against its own edited training images inside the selection,
      and, at held-out cameras, the IoU of its opacity (alpha > 0.5) with the proxy's silhouette
      and its mean opacity inside that silhouette.
    clip_directional_similarity: of the edited-NeRF renders (when CLIP weights were given).
  """
  relative = ("consistency", "relative_to_original")
  return {
      "background_psnr": _get(metrics, "background", "psnr_paper"),
      "background_ssim": _get(metrics, "background", "ssim_paper"),
      "consistency_change": _get(metrics, *relative, "sheet_propagated", "mean_epipolar_inliers"),
      "independent_consistency_change": _get(metrics, *relative, "independent",
                                             "mean_epipolar_inliers"),
      "prompt_color_share": _get(metrics, "prompt_color_adherence", "nerf_renders", "share"),
      "shape_iou": _get(metrics, "shape_iou", "nerf_renders"),
      "edited_images_shape_iou": _get(metrics, "shape_iou", "image_set"),
      "fit_psnr": _get(metrics, "nerf_consistency", "fit_psnr", "mean"),
      "solidity_iou": _get(metrics, "nerf_consistency", "solidity", "iou", "mean"),
      "solidity_opacity": _get(metrics, "nerf_consistency", "solidity", "mean_opacity", "mean"),
      "clip_directional_similarity": _get(metrics, "clip_directional_similarity", "nerf"),
  }


def summarize_edit(edit: stages.EditContext) -> dict[str, Any]:
  """A finished edit's quality (`edit_quality`) and times in seconds.

  Returns:
    directory, quality, stage_seconds;
    edit_seconds: the stages' total without `SHARED_STAGES`;
    edited_views: views that show the selection (the image set update's work);
    seconds_per_view: {"sheet_propagated": the `PROPAGATION_STAGES`' seconds per edited view,
      "independent": the evaluation's independent edits' seconds per view (None without them)}.
  """
  metrics = files.read_json(edit.directory.path("evaluation", "metrics.json"))
  stage_seconds = edit.directory.stage_seconds()
  edited_views = len(edit.visible_views())
  independent = metrics.get("independent_edits")
  return {
      "directory": str(edit.directory.root),
      "quality": edit_quality(metrics),
      "edit_seconds": sum(seconds for name, seconds in stage_seconds.items()
                          if name not in SHARED_STAGES),
      "stage_seconds": stage_seconds,
      "edited_views": edited_views,
      "seconds_per_view": {
          "sheet_propagated": sum(stage_seconds.get(name, 0.0) for name in PROPAGATION_STAGES)
                              / max(edited_views, 1),
          "independent": independent["seconds"] / independent["views"] if independent else None,
      },
  }


class Sweep:
  """Edits sharing common gin settings and one original NeRF, each distinct edit run once.

  Attributes:
    root: holds original/ (the shared NeRF's edit directory) and the runs, GROUP/VARIANT/.
    gin_files, bindings: the common settings, parsed before each variant's bindings (after
      `train_original`, the bindings name the trained NeRF).
    progress, log: as `stages.run_edit`'s; log lines are prefixed with the variant.
  """

  def __init__(self, root: str | Path, gin_files: Sequence[str], bindings: Sequence[str],
               progress: bool = True, log: Callable[[str], None] = print):
    self.root = Path(root)
    self.gin_files = list(gin_files)
    self.bindings = list(bindings)
    self.progress = progress
    self.log = log
    self._summaries: dict[str, dict[str, Any]] = {}

  def train_original(self) -> dict[str, Any]:
    """Trains (or resumes, or reuses) the original NeRF in ROOT/original; every later variant
    uses it. Returns {"run": its run directory, "seconds": the stage's wall time}."""
    configs.parse_gin(self.gin_files, self.bindings)
    directory = self.root / "original"
    settings = commands.edit_settings()
    with stages.claimed_edit(directory, settings):
      configs.save_gin_config(directory)
      edit = stages.run_edit(directory, settings, until="original",
                             progress=self.progress,
                             log=lambda line: self.log(f"original NeRF {line}"))
    run_dir = edit.original_run_dir.resolve()
    self.bindings.append(f"EditConfig.original_run = {str(run_dir)!r}")
    return {"run": str(run_dir), "seconds": edit.directory.stage_seconds()["original"]}

  def run(self, group: str, variant: Variant) -> dict[str, Any]:
    """Runs (or resumes) the variant in ROOT/group/name unless an edit with the same pipeline
    key ran before; returns its name, bindings and summary (`summarize_edit`), plus "same_as":
    the directory of the earlier run it shares, if any."""
    configs.parse_gin(self.gin_files, self.bindings + list(variant.bindings))
    directory = self.root / group / variant.name
    settings = commands.edit_settings()
    key = canonical_json(stages.edit_key(directory, settings))
    result = {"name": variant.name, "bindings": list(variant.bindings)}
    if key in self._summaries:
      earlier = self._summaries[key]
      self.log(f"{group}/{variant.name}: the same edit as {earlier['directory']}")
      return {**result, **earlier, "same_as": earlier["directory"]}
    jax.clear_caches()
    with stages.claimed_edit(directory, settings):
      configs.save_gin_config(directory)
      edit = stages.run_edit(directory, settings, progress=self.progress,
                             log=lambda line: self.log(f"{group}/{variant.name} {line}"))
    self._summaries[key] = summarize_edit(edit)
    return {**result, **self._summaries[key]}
