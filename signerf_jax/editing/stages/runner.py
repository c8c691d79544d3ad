"""The stage runner: order, keys, resume, timing and progress lines.

A stage's *key* is the settings it reads plus the keys of the stages it builds on. `run_edit`
skips a stage whose recorded key is current and redoes it (clearing its folders) otherwise, so
changing, say, the sheet recipe redoes the sheet and everything after it while the NeRF and the
renders stay.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from pathlib import Path
from typing import Any, Callable

from signerf_jax import files, ownership
from signerf_jax.editing.config import EditSettings, as_json
from signerf_jax.editing.project import EditDirectory, canonical_json
from signerf_jax.editing.stages import evaluate, inputs, nerf_update, propagation, reference
from signerf_jax.editing.stages import sheets
from signerf_jax.editing.stages.context import EditContext
from signerf_jax.errors import InputError

STAGE_KEY_FILE = ".stage_key.json"

# How a stage that trains a NeRF is run: (stage, context) -> its summary line. None: in this
# process, as every other stage (`signerf`'s edit commands on a CPU pass one that runs it in a
# process of its own, `editing.commands.training_process`).
RunTraining = Callable[["Stage", EditContext], str]


@dataclasses.dataclass(frozen=True)
class Stage:
  """A pipeline stage.

  Attributes:
    name: as in stages.json and `run_edit(until=...)`.
    run: does the work; returns the one-line summary.
    settings: what the stage reads (part of its key).
    after: the stages whose outputs it uses (their keys are part of its key).
    folders: the edit directory's folders it writes (relative, with the iteration), cleared
      when the stage is redone with another key.
    description: what it does, shown while it runs.
    iteration: the edit iteration it belongs to.
    trains_nerf: the NeRF it trains (0: the original, else the iteration's edited one; None:
      it trains none).
  """

  name: str
  run: Callable[[EditContext], str]
  settings: Callable[[EditContext], Any]
  after: tuple[str, ...]
  folders: tuple[str, ...]
  description: str
  iteration: int = 1
  trains_nerf: int | None = None

  def outputs(self, context: EditContext) -> tuple[Path, ...]:
    return tuple(context.directory.path(name, iteration=self.iteration) for name in self.folders)


def _no_settings(context: EditContext) -> dict[str, Any]:
  del context  # What the stage does depends only on the stages it builds on.
  return {}


def _iteration_stages(iteration: int) -> list[Stage]:
  """Steps 4-7 of one iteration (the second starts from the first's edited NeRF)."""
  suffix = "" if iteration == 1 else f"_{iteration}"
  previous = ("finetune",) if iteration == 2 else ()
  bind = lambda function: functools.partial(function, iteration=iteration)  # noqa: E731
  stages = [Stage(f"reference{suffix}", bind(reference.render_reference),
                  reference.reference_settings,
                  ("original", "select") + previous + (("reference",) if previous else ()),
                  ("reference",), "placing the reference cameras and rendering their tiles",
                  iteration)]
  if iteration == 1:
    stages.append(Stage("preview", sheets.preview, sheets.preview_settings, ("reference",), (),
                        "generating candidate sheets"))
  stages.append(Stage(f"sheet{suffix}", bind(sheets.generate_sheet), bind(sheets.sheet_settings),
                      (f"reference{suffix}",), ("sheet",), "generating the chosen sheet",
                      iteration))
  if iteration == 1:
    # Only the update needs every view's mask and control: the preview comes first, quicker.
    stages.append(Stage("views", inputs.condition_views, inputs.view_settings,
                        ("original", "select"), ("views",),
                        "rendering every training view's mask and control depth near the "
                        "selection"))
  return stages + [
      Stage(f"update{suffix}", bind(propagation.update_image_set),
            bind(propagation.update_settings), (f"sheet{suffix}", "views") + previous,
            ("update",), "updating every view through the sheet's slot", iteration),
      Stage(f"dataset{suffix}", bind(propagation.write_dataset), _no_settings,
            (f"update{suffix}",), ("dataset",), "writing the edited dataset", iteration),
      Stage(f"finetune{suffix}", bind(nerf_update.update_nerf),
            bind(nerf_update.finetune_settings),
            (f"dataset{suffix}",) + (previous or ("original",)), ("edited",),
            "updating the NeRF on the edited views", iteration, trains_nerf=iteration),
  ]


def pipeline_stages(settings: EditSettings) -> list[Stage]:
  """The stages in order (with the second iteration's when enabled)."""
  second = settings.edit.second_iteration
  stages = [
      Stage("original", inputs.train_original, inputs.original_settings, (),
            () if settings.edit.original_run else ("original",),
            "loading the given trained NeRF" if settings.edit.original_run
            else "training the original NeRF",
            trains_nerf=None if settings.edit.original_run else 0),
      Stage("select", inputs.select, lambda context: as_json(context.settings.selection),
            ("original",), ("selection",), "building the selection"),
      *_iteration_stages(1),
      *(_iteration_stages(2) if second else []),
  ]
  stages.append(Stage("evaluate", evaluate.evaluate_edit, evaluate.evaluation_settings,
                      ("finetune_2" if second else "finetune", "views"), ("evaluation",),
                      "evaluating the edit"))
  return stages


def stage_keys(stages: list[Stage], context: EditContext) -> dict[str, Any]:
  """name -> the stage's key: its settings and the keys of the stages it builds on (`stages`
  in order, each after the ones it builds on)."""
  keys: dict[str, Any] = {}
  for stage in stages:
    keys[stage.name] = {"settings": stage.settings(context),
                        "after": {name: keys[name] for name in stage.after}}
  return keys


def edit_key(directory, settings: EditSettings) -> dict[str, Any]:
  """The key of the whole edit (its last stage's): equal keys mean the same edit."""
  context = EditContext(EditDirectory(directory), settings)
  return stage_keys(pipeline_stages(settings), context)["evaluate"]


def _prepare_folder(path: Path, key: Any) -> None:
  """Clears what the project wrote in `path` unless it holds the outputs of a run with this
  key; marks it with the key.

  The same key means an interrupted run of the same stage: its finished files are kept. Files
  the project did not write stay wherever they are (`ownership.remove_written`).
  """
  marker = path / STAGE_KEY_FILE
  current = canonical_json(key)
  if path.is_dir() and (not marker.is_file() or marker.read_text() != current):
    ownership.remove_written(path)
  path.mkdir(parents=True, exist_ok=True)
  if not marker.is_file():
    files.write_text(marker, current)


def _with_dependents(stages: list[Stage], names) -> set[str]:
  """`names` and every stage that builds on one of them, directly or not."""
  chosen = set(names)
  for stage in stages:
    if chosen.intersection(stage.after):
      chosen.add(stage.name)
  return chosen


def _start(directory, settings: EditSettings, until: str, redo: tuple[str, ...],
           progress: bool, log: Callable[[str], None]) -> tuple[EditContext, list[Stage]]:
  """The context and the stages to run, once the directory is claimed: clears what `redo` asks
  to redo."""
  stages = pipeline_stages(settings)
  context = EditContext(EditDirectory(directory), settings, progress)
  context = dataclasses.replace(context, keys=stage_keys(stages, context))
  redone = _with_dependents(stages, redo)
  for stage in stages:
    if stage.name in redone:
      for folder in stage.outputs(context):
        ownership.remove_written(folder)
  context.directory.forget(redone)
  stages = stages[:[stage.name for stage in stages].index(until) + 1]
  to_run = tuple(stage.name for stage in stages
                 if not context.directory.is_finished(stage.name, context.keys[stage.name]))
  return dataclasses.replace(context, stages_to_run=to_run), stages


def _check(settings: EditSettings, until: str, redo: tuple[str, ...],
           log: Callable[[str], None]) -> None:
  """Checks the stage names and the inputs (logging any warning) before anything is written."""
  names = [stage.name for stage in pipeline_stages(settings)]
  for name in (until, *redo):
    if name not in names:
      raise InputError(f"unknown stage {name!r} (stages: {', '.join(names)})", field="stage")
  for warning in inputs.check_inputs(settings):
    log(f"warning: {warning}")


def run_edit(directory, settings: EditSettings, until: str = "evaluate",
             redo: tuple[str, ...] = (), progress: bool = True,
             log: Callable[[str], None] = print,
             run_training: RunTraining | None = None) -> EditContext:
  """Runs (or resumes) the pipeline in `directory` up to and including stage `until`, with
  `settings`.

  Args:
    until: the last stage to run.
    redo: stages to run again from scratch even when their key is current (with every stage
      that builds on them).
    progress: show progress bars.
    log: receives one line as each stage starts and ends.
    run_training: runs the stages that train a NeRF (None: as the others, `Stage.run`).
  Returns:
    The run's context (its directory, settings and loaded inputs).
  """
  _check(settings, until, tuple(redo), log)
  with claimed_edit(directory, settings):
    return _run_stages(directory, settings, until, tuple(redo), progress, log, run_training)


def claimed_edit(directory, settings: EditSettings):
  """`ownership.claimed` for an edit directory: refused where it overlaps what the edit reads
  (the dataset, the original run, the diffusion model); a context manager."""
  edit = settings.edit
  return ownership.claimed(directory, ownership.EDIT, inputs=(
      ("data", edit.data), ("run", edit.original_run), ("model", edit.model),
      ("controlnet", edit.controlnet)))


def _run_stages(directory, settings: EditSettings, until: str, redo: tuple[str, ...],
                progress: bool, log: Callable[[str], None],
                run_training: RunTraining | None) -> EditContext:
  context, stages = _start(directory, settings, until, redo, progress, log)
  for number, stage in enumerate(stages, 1):
    key = context.keys[stage.name]
    label = f"[{number}/{len(stages)}] {stage.name}"
    if stage.name not in context.stages_to_run:
      summary = context.directory.record(stage.name).summary
      log(f"{label}: reusing its earlier result - {summary}")
      continue
    log(f"{label}: {stage.description} ...")
    for folder in stage.outputs(context):
      _prepare_folder(folder, key)
    start = time.perf_counter()
    if run_training is not None and stage.trains_nerf is not None:
      summary = run_training(stage, context)
    else:
      summary = stage.run(context)
    seconds = time.perf_counter() - start
    context.directory.finish(stage.name, key, seconds, summary)
    log(f"{label}: {summary} ({seconds:.1f} s)")
  return context
