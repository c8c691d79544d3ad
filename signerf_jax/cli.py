"""The `signerf` command: one subcommand per pipeline stage.

Each subcommand lives in the module that owns its stage and exposes `add_arguments(parser)` and
`run(args) -> int`. Only the chosen subcommand's module is imported, so `signerf --help` is fast.

One flag name per thing, in every command: --data the input dataset, --run a NeRF run directory
(`signerf train` writes it, the others read it), --edit an edit directory, --out only the folder
a command fills with outputs that are neither (synthesize's dataset, render's renders, the
demo's folder). Old spellings stay for a release as deprecated aliases (`deprecated_aliases`).
"""

from __future__ import annotations

import argparse
import functools
import importlib
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Sequence

from signerf_jax import allocator, ownership
from signerf_jax.errors import InputError

# name -> (module implementing it, one-line help). Stages add themselves here.
COMMANDS: dict[str, tuple[str, str]] = {
    "synthesize": ("signerf_jax.data.commands.synthesize",
                   "write a synthetic scene with ground-truth depth and object masks"),
    "process": ("signerf_jax.data.commands.process",
                "recover the camera poses of photos or a video (COLMAP) and write a dataset"),
    "train": ("signerf_jax.nerf.commands.train", "train (or resume) a NeRF on a dataset"),
    "render": ("signerf_jax.nerf.commands.render",
               "render a trained NeRF's views (PNG, depth EXR) and a camera-path video"),
    "eval": ("signerf_jax.editing.commands.evaluate",
             "evaluate a trained NeRF (PSNR, SSIM, depth error) or an edit (--edit) as one "
             "JSON line"),
    "edit": ("signerf_jax.editing.commands.edit",
             "edit a NeRF scene with a prompt (SIGNeRF): every stage, resumable"),
    "info": ("signerf_jax.nerf.commands.info",
             "a trained run's scene frame, bounds, views and a default proxy size"),
    "place": ("signerf_jax.editing.commands.place",
              "stand a proxy on the surface under a pixel of a training view"),
    "preview": ("signerf_jax.editing.commands.preview",
                "preview candidate reference sheets (seeds side by side, per-tile re-rolls)"),
    "update": ("signerf_jax.editing.commands.edit",
               "update the image set through the chosen sheet; write the edited dataset"),
    "finetune": ("signerf_jax.editing.commands.edit",
                 "fine-tune (or retrain) the NeRF on the edited dataset"),
    "view": ("signerf_jax.viewer.command",
             "the trained NeRF, its cameras and the edit's selection in a browser: move the "
             "selection, preview sheets, save"),
    "demo": ("signerf_jax.editing.demo",
             "insert a cow into a generated scene with the shipped model, end to end"),
}

# name -> what the command writes, where (its --help description, after the one-line help).
WRITES: dict[str, str] = {
    "synthesize": "Writes OUT: a nerfstudio dataset (transforms.json, images/, depths/ as EXR "
                  "z-depth, object_masks/), scene.json (the scene and how it was made) and "
                  "config.gin.",
    "process": "Writes OUT: a nerfstudio dataset: images/ (upright photos or a video's sharpest "
               "frames), images_2/, images_4/, images_8/, colmap/ (database.db, which a rerun "
               "reuses, and sparse/0/, the model), transforms.json (the registered images) and "
               "process.json (the summary, also printed as one JSON line). A rerun resumes.",
    "train": "Writes RUN: config.gin (the gin bindings, which a resume reads back), model.json, "
             "checkpoint.msgpack, schedule.json (the schedule's progress at each step, which "
             "--replay reads), and after training eval.json and eval/ (held-out renders and "
             "depth maps). A rerun resumes.",
    "render": "Writes OUT (default RUN/renders): SPLIT/<view>.png, .depth.exr, .depth.png and "
              ".accumulation.png, and with --video video.mp4.",
    "eval": "Writes RUN/eval.json and RUN/eval/ (the held-out renders), or with --edit "
            "EDIT/evaluation/ (metrics.json, before/after figures, video) after running any "
            "unfinished stage.",
    "edit": "Writes EDIT: config.gin (the edit's settings, read first by every later command), "
            "stages.json and one folder per stage: original/ (unless --run), selection/, "
            "reference/, preview/, sheet/, views/, update/, dataset/ (the edited dataset), "
            "edited/ (the edited NeRF), evaluation/ (iteration_2/ with --second_iteration). "
            "Finished stages are skipped on a rerun.",
    "info": "Writes nothing: prints the scene in the dataset's own units on stderr and as one "
            "JSON line on stdout.",
    "place": "Writes EDIT/config.gin (the selection as gin bindings, on top of the edit's saved "
             "settings) and EDIT/placement.png (the view with the selection's silhouette); prints "
             "the selection as one JSON line.",
    "preview": "Writes EDIT/preview/: candidates/ (one sheet per seed or re-roll) and preview.png "
               "(them side by side), after the stages before it (original/ unless --run, "
               "selection/, reference/) and EDIT/config.gin.",
    "update": "Writes EDIT/update/ (the edited views) and EDIT/dataset/ (the edited dataset), "
              "after the stages before them (as `signerf edit`) and EDIT/config.gin.",
    "finetune": "Writes EDIT/edited/ (the edited NeRF, a run directory), after the stages before "
                "it (as `signerf edit`) and EDIT/config.gin.",
    "view": "Writes EDIT/config.gin when the selection and settings are saved, and "
            "EDIT/preview/ (as `signerf preview`) when sheets are previewed; nothing else.",
    "demo": "Writes OUT: scene/ (the synthetic scene, as `signerf synthesize`) and edit/ (the "
            "edit, as `signerf edit`; edit/evaluation/ holds the before/after figure, the sheet, "
            "the video and metrics.json). A rerun resumes.",
}

# The dataset formats `data.load_dataset` reads (`data.load.FORMATS`), for every --data help.
DATA_FORMATS = "nerfstudio, Blender, LLFF, COLMAP or NeuS/IDR"
DATA_HELP = f"dataset directory ({DATA_FORMATS}; the format is detected)"

# Commands whose process keeps the memory XLA frees (signerf_jax.allocator): a NeRF step or a
# rendered chunk frees and re-faults its buffers on every call (`eval --run` renders the views it
# measures); and `view`, whose frames come sooner while its occasional preview samples slower.
# The edit commands (`edit`, `preview`, `update`, `finetune`, `eval --edit`, `demo`) do not: their
# sampling, renders and compilations are faster without, and their NeRF trainings run in a
# process of their own that keeps it (`editing.commands.training_process`; docs/performance.md).
KEEP_FREED_MEMORY_COMMANDS = ("train", "render", "eval", "view")


def keeps_freed_memory(args: argparse.Namespace) -> bool:
  """Whether the command `args` asks for keeps freed memory in its own process."""
  if args.command == "eval" and args.edit:
    return False  # An edit's evaluation: it samples and compiles more than it renders.
  return args.command in KEEP_FREED_MEMORY_COMMANDS


# Commands that run under jax.distributed when asked (`distributed`): their computations split
# over the devices of every process.
DISTRIBUTED_COMMANDS = ("train", "edit", "update", "finetune")

# Commands a rerun resumes (checkpoints and finished stages are kept): an interrupted one says so.
RESUMABLE_COMMANDS = ("process", "train", "edit", "update", "finetune", "demo")


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
  """Every option's help ends with its default, unless the help says it already ("default")
  or there is none to show: None or "" (the flag sets nothing unless given; its help says what
  happens then), False (a switch) or [] (a repeatable flag, none given)."""

  def _get_help_string(self, action: argparse.Action) -> str | None:
    default = action.default
    if (default is None or default is False or (isinstance(default, (list, str)) and not default)
        or "default" in (action.help or "")):
      return action.help
    return super()._get_help_string(action)


def deprecated_aliases(parser: argparse.ArgumentParser, action: argparse.Action,
                       *old_flags: str) -> argparse.Action:
  """Lets each of `old_flags`, an old spelling of `action`'s flag, stand for it for one more
  release: it parses as the flag does, and prints one warning line naming the flag ("signerf
  train: --out is deprecated, use --run"). --help shows the new flag only. Returns `action`.

  `parser` is the parser or argument group `action` was added to."""
  for old_flag in old_flags:
    if old_flag in parser._option_string_actions:  # pylint: disable=protected-access
      raise ValueError(f"{old_flag} is already a flag here")
    parser._option_string_actions[old_flag] = action  # pylint: disable=protected-access
  action.deprecated_aliases = (*getattr(action, "deprecated_aliases", ()), *old_flags)
  action.__class__ = _warning_on_aliases(type(action))
  return action


@functools.cache
def _warning_on_aliases(action_class: type[argparse.Action]) -> type[argparse.Action]:
  """`action_class`, warning when an action is given by one of its `deprecated_aliases`."""

  class Renamed(action_class):
    def __call__(self, parser, namespace, values, option_string=None):
      if option_string in self.deprecated_aliases:
        print(f"{parser.prog}: {option_string} is deprecated, use {self.option_strings[0]}",
              file=sys.stderr)
      super().__call__(parser, namespace, values, option_string)

  Renamed.__name__ = Renamed.__qualname__ = f"Renamed{action_class.__name__}"
  return Renamed


def add_output_argument(parser: argparse.ArgumentParser, flag: str, *,
                        deprecated: Sequence[str] = (), **kwargs) -> argparse.Action:
  """Adds `flag` (keyword arguments as `add_argument`'s), the directory the command writes:
  `main` checks it can be written before the command starts, naming the flag. `deprecated`:
  old spellings (`deprecated_aliases`)."""
  parser.set_defaults(output_flag=flag.lstrip("-"))
  return deprecated_aliases(parser, parser.add_argument(flag, **kwargs), *deprecated)


def build_parser(argv: Sequence[str]) -> argparse.ArgumentParser:
  """The `signerf` parser; only the subcommand named first in `argv` adds its options."""
  # No abbreviations: each flag has one spelling (preview's --seeds is not `edit --seed`).
  parser = argparse.ArgumentParser(prog="signerf", description=__doc__.splitlines()[0],
                                   formatter_class=HelpFormatter, allow_abbrev=False)
  subparsers = parser.add_subparsers(dest="command", required=True)
  for name, (module_name, help_text) in COMMANDS.items():
    description = f"{help_text[0].upper()}{help_text[1:]}. {WRITES.get(name, '')}".strip()
    subparser = subparsers.add_parser(name, help=help_text, description=description,
                                      formatter_class=HelpFormatter, allow_abbrev=False)
    subparser.set_defaults(module_name=module_name)
    if argv and argv[0] == name:
      importlib.import_module(module_name).add_arguments(subparser)
      if name in DISTRIBUTED_COMMANDS:
        from signerf_jax import distributed  # pylint: disable=g-import-not-at-top
        distributed.add_arguments(subparser)
  return parser


def use_compilation_cache() -> None:
  """Keeps compiled programs between commands in JAX's persistent cache, so a preview after
  `signerf train`, or the next preview, does not compile the sampler and the renderer again
  (docs/performance.md). JAX's own settings win: JAX_COMPILATION_CACHE_DIR
  chooses another directory, JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS another threshold,
  JAX_ENABLE_COMPILATION_CACHE=false turns the cache off."""
  import jax  # pylint: disable=g-import-not-at-top  (`signerf --help` stays fast without it)
  if jax.config.jax_compilation_cache_dir is None:
    cache_home = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    jax.config.update("jax_compilation_cache_dir", str(cache_home / "signerf_jax" / "xla"))
  if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ:
    # A preview compiles many small programs, most under JAX's default 1 s threshold, which
    # together take seconds.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.1)


def raise_terminated(signum: int, frame) -> None:
  """SIGTERM's handler while a command runs: stops it as Ctrl-C does (`training_loop`)."""
  del signum, frame
  from signerf_jax import training_loop  # pylint: disable=g-import-not-at-top  (already loaded)
  raise training_loop.Terminated()


def _run_command(module, args: argparse.Namespace, output_flag: str | None) -> int:
  """`module.run(args)`, in each process of a run of several when the command joins one
  (`distributed`: only process 0 writes the outputs)."""
  from signerf_jax import distributed, parallel  # pylint: disable=g-import-not-at-top
  joined = distributed.settings(args) if args.command in DISTRIBUTED_COMMANDS else None
  if joined is not None:
    parallel.initialize_distributed(*joined)
  with distributed.private_outputs(args, output_flag):
    return int(module.run(args) or 0)


def main(argv: Sequence[str] | None = None) -> int:
  """Runs the subcommand `argv` names; returns its exit code: 2 with a message on bad input;
  130 / 143 with one line after SIGINT / SIGTERM (a training run checkpoints its steps first
  and the line names the step and where it was saved)."""
  argv = list(sys.argv[1:] if argv is None else argv)
  args = build_parser(argv).parse_args(argv)
  if keeps_freed_memory(args):
    allocator.keep_freed_memory()  # Before JAX starts its threads.
  # Here, not at the top: `signerf --help` stays fast without tqdm.
  from signerf_jax import training_loop  # pylint: disable=g-import-not-at-top
  # SIGTERM (a scheduler's or `kill`'s stop) ends a command as Ctrl-C does, not unannounced and
  # mid-write. Not `view`'s: it stops its server on Ctrl-C only, and SIGTERM's default exit is
  # as clean for it.
  catch_sigterm = (args.command != "view"
                   and threading.current_thread() is threading.main_thread())
  previous_sigterm = signal.signal(signal.SIGTERM, raise_terminated) if catch_sigterm else None
  try:
    module = importlib.import_module(args.module_name)
    output_flag = getattr(args, "output_flag", None)  # `add_output_argument`'s.
    if output_flag and getattr(args, output_flag, None):
      ownership.check_output_path(getattr(args, output_flag), output_flag)
    use_compilation_cache()
    return _run_command(module, args, output_flag)
  except InputError as error:
    print(f"signerf {args.command}: error: {error}", file=sys.stderr)
    return 2
  except training_loop.TrainingInterrupted as interruption:
    print(f"signerf {args.command}: {interruption}", file=sys.stderr)
    return interruption.exit_code
  except (KeyboardInterrupt, training_loop.Terminated) as error:
    # Outside a training loop (loading, compiling, an edit's sampling stages): what is written
    # is written atomically, and the resumable commands pick up from it.
    resume = "; run the same command to resume" if args.command in RESUMABLE_COMMANDS else ""
    print(f"signerf {args.command}: interrupted{resume}", file=sys.stderr)
    return 128 + int(training_loop.signal_of(error))
  finally:
    if catch_sigterm:
      signal.signal(signal.SIGTERM, previous_sigterm)


if __name__ == "__main__":
  sys.exit(main())
