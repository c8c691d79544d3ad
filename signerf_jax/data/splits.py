"""Which views are trained on and which are held out for evaluation.

In order of precedence:
  1. an explicit list of held-out image names (`held_out`);
  2. `eval_every = N`: every N-th view held out, starting with the first (NeRF's LLFF hold-out);
  3. the source's own split: nerfstudio's `train_filenames` / `val_filenames` /
     `test_filenames`, or `transforms_{train,val,test}.json` files;
  4. every 8th view.
Held-out views never reach the training split: the two are disjoint by construction, and a
source that lists a view in both is an error.
"""

from __future__ import annotations

import os
from pathlib import PurePosixPath
from typing import Sequence

import numpy as np

from signerf_jax.errors import InputError

SPLITS = ("train", "eval", "all")
DEFAULT_EVAL_EVERY = 8


def name_key(name: str) -> str:
  """A name as the views are matched: POSIX, without a leading "./" and without extension."""
  path = PurePosixPath(str(name).replace("\\", "/"))
  parts = [part for part in path.parts if part != "."]
  return str(PurePosixPath(*parts).with_suffix("")) if parts else ""


def match_names(names: Sequence[str], wanted: Sequence[str], path=None,
                field: str = "held_out") -> np.ndarray:
  """Indices into `names` of each name in `wanted` (compared by `name_key`; a bare file name
  matches when it is unique).

  Raises:
    InputError: naming the wanted names that match no view, or more than one.
  """
  keys = [name_key(name) for name in names]
  by_key = {key: index for index, key in enumerate(keys)}
  by_stem: dict[str, list[int]] = {}
  for index, key in enumerate(keys):
    by_stem.setdefault(PurePosixPath(key).name, []).append(index)
  indices, unknown, ambiguous = [], [], []
  for name in wanted:
    key = name_key(name)
    if key in by_key:
      indices.append(by_key[key])
    elif len(by_stem.get(key, [])) == 1:
      indices.append(by_stem[key][0])
    elif key in by_stem:
      ambiguous.append(str(name))
    else:
      unknown.append(str(name))
  if unknown or ambiguous:
    problems = []
    if unknown:
      problems.append(f"no view is named {', '.join(unknown[:5])}"
                      + (f" (and {len(unknown) - 5} more)" if len(unknown) > 5 else ""))
    if ambiguous:
      problems.append(f"several views end in {', '.join(ambiguous[:5])}")
    raise InputError("; ".join(problems) + f" (views are named like {names[0]!r})", path, field)
  return np.asarray(sorted(set(indices)), np.int64)


def select_views(names: Sequence[str], split: str, *,
                 source_splits: dict[str, Sequence[int]] | None = None,
                 eval_every: int | None = None, held_out: Sequence[str] = (),
                 path=None) -> np.ndarray:
  """Indices of the views in `split` ("train", "eval" or "all"), sorted.

  Args:
    names: every view's name, in the source's order.
    split: which views to return.
    source_splits: the source's own {"train": indices, "eval": indices}, or None.
    eval_every: hold out every N-th view (N >= 2) instead of the source's split.
    held_out: names of the views to hold out (wins over everything else).
    path: the dataset, for errors.
  """
  if split not in SPLITS:
    raise InputError(f"must be one of {SPLITS}, got {split!r}", field="split")
  count = len(names)
  everything = np.arange(count)
  if split == "all":
    return everything
  from_source = not held_out and eval_every is None and source_splits is not None
  if held_out:
    evaluation = match_names(names, held_out, path)
    training = np.setdiff1d(everything, evaluation)
  elif not from_source:
    period = DEFAULT_EVAL_EVERY if eval_every is None else eval_every
    if isinstance(period, bool) or not isinstance(period, (int, np.integer)) or period < 2:
      raise InputError(f"must be a whole number of at least 2, got {period!r}",
                       field="eval_every")
    evaluation = everything[everything % period == 0]
    training = everything[everything % period != 0]
  else:
    training = np.unique(np.asarray(source_splits.get("train", ()), np.int64))
    evaluation = np.unique(np.asarray(source_splits.get("eval", ()), np.int64))
    both = np.intersect1d(training, evaluation)
    if both.size:
      raise InputError(f"{both.size} views are listed for both training and evaluation, e.g. "
                       f"{names[int(both[0])]!r}", path, "train_filenames")
  chosen = training if split == "train" else evaluation
  if chosen.size == 0 and from_source:
    # No eval_every was given: blaming it would send the user after a flag they never set.
    raise InputError(f"the {split} split is empty: the dataset's own split puts none of its "
                     f"{count} views in it; choose views to hold out with eval_every or "
                     "held_out", path)
  if chosen.size == 0:
    raise InputError(f"the {split} split is empty ({count} views; the hold-out leaves none)",
                     path, "held_out" if held_out else "eval_every")
  return chosen


def check_listed_once(listed: Sequence[tuple[str | os.PathLike, str, str]]) -> None:
  """Refuses an image listed twice, as the same path or spelt differently (`./images/a.png`,
  `images/a`): the view would count twice, and split keys, which name views by their path,
  could not tell the two entries apart.

  Args:
    listed: (file, entry, image path) of each listed image, e.g. (transforms.json,
      "frames[3].file_path", "images/a.png").
  Raises:
    InputError naming the file and the second entry, and the first.
  """
  first_entry = {}
  for path, field, name in listed:
    key = name_key(name)
    if key in first_entry:
      raise InputError(f"{name!r} names the same image as {first_entry[key]}; list each view "
                       "once", path, field)
    first_entry[key] = field
