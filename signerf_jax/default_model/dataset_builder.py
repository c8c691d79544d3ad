"""The default model's data on disk: sharded, resumable, deterministic per sample.

Layout of the output directory:
  manifest.json                       what was generated, with which settings, how fast;
  config.gin                          the gin bindings it was generated with;
  tokenizer/                          the word tokenizer over every caption word (diffusers
                                      layout; ship it with the trained weights);
  <split>/<kind>/shard_<index>.npz    split "train" or "eval", kind "sheets" or "singles".

A shard is `np.savez_compressed` of `samples.Sample.arrays()` stacked over its S samples (so
`rgb` is [S, V, H, W, 3] with V = 1 for singles and sheet_tiles + 1 for sheets; strings are
numpy unicode arrays, nothing is pickled), plus
  sample_index [S] int64   the samples' indices within their split and kind;
  shard_info   []  str     JSON: split, kind, shard, first_sample, samples, fingerprint.
Sample i of (split, kind) is drawn from `np.random.default_rng([split seed, kind code, i])`, so
it does not depend on the shard size, on the order shards are made in, or on how many workers
make them. The "eval" split uses `eval_seed` (held out from "train") and balanced attributes:
sample i shows colour i mod 8, pattern (i div 8) mod 4 and kind i mod K (K = kinds available),
so every colour, pattern and kind is evaluated equally often; these are the fixed evaluation
scenes. Train attributes are uniformly random.

Resuming: a shard is written atomically (temporary file, then rename); a later run skips every
shard that exists with the same fingerprint (a hash of the scene, caption and seed settings and
of the object catalogue) and the same sample range, so interrupting and re-running loses at most
the shards in progress, and raising the sample counts only adds shards. A shard made with other
settings is an error rather than silently mixed in. The manifest is rewritten after every shard.

Reading: `read_shard(path)` (all arrays of one shard) and `iterate_batches` (shuffled batches
over a split and kind, one shard in memory at a time); `signerf_jax.default_model.batches` turns
them into model inputs.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import hashlib
import json
import multiprocessing
import os
import time
from pathlib import Path
from typing import Any, Callable, Iterator

import gin
import numpy as np
import tqdm

from signerf_jax import configs
from signerf_jax import files
from signerf_jax.clip import word_tokenizer
from signerf_jax.default_model import appearance
from signerf_jax.default_model import captions
from signerf_jax.default_model import samples
from signerf_jax.default_model import scenes
from signerf_jax.errors import InputError
from signerf_jax.metrics import colors

FORMAT = "signerf-default-model-data"
VERSION = 1
MANIFEST_NAME = "manifest.json"
TOKENIZER_FOLDER = "tokenizer"
SPLITS = ("train", "eval")
KINDS = ("sheets", "singles")
KIND_CODES = {"sheets": 0, "singles": 1}


@gin.configurable("default_model_data")
@dataclasses.dataclass(frozen=True)
class DataSettings:
  """How much data to make and where (gin: `default_model_data.<field>`).

  Attributes:
    output_directory: where the dataset goes.
    seed, eval_seed: seeds of the train and the held-out eval split (must differ).
    num_sheets, num_singles: train samples of each kind.
    num_eval_sheets, num_eval_singles: eval samples of each kind.
    sheets_per_shard, singles_per_shard: samples per shard file.
    tokenizer_max_length: the word tokenizer's output length (the text encoder's
      max_position_embeddings).
  """

  output_directory: str = ""
  seed: int = 0
  eval_seed: int = 1_000_003
  num_sheets: int = 4000
  num_singles: int = 8000
  num_eval_sheets: int = 64
  num_eval_singles: int = 256
  sheets_per_shard: int = 50
  singles_per_shard: int = 250
  tokenizer_max_length: int = word_tokenizer.DEFAULT_MAX_LENGTH

  def split_seed(self, split: str) -> int:
    return self.seed if split == "train" else self.eval_seed

  def count(self, split: str, kind: str) -> int:
    prefix = "num_eval_" if split == "eval" else "num_"
    return getattr(self, prefix + kind)

  def per_shard(self, kind: str) -> int:
    return getattr(self, f"{kind}_per_shard")


@dataclasses.dataclass(frozen=True)
class ShardSpec:
  """One shard to make: samples first_sample .. first_sample + samples - 1 of (split, kind)."""

  split: str
  kind: str
  index: int
  first_sample: int
  samples: int
  seed: int
  fingerprint: str

  @property
  def relative_path(self) -> str:
    return f"{self.split}/{self.kind}/shard_{self.index:05d}.npz"

  def info(self) -> dict[str, Any]:
    return {"split": self.split, "kind": self.kind, "shard": self.index,
            "first_sample": self.first_sample, "samples": self.samples,
            "fingerprint": self.fingerprint}


def fingerprint(settings: DataSettings, scene_sampling: scenes.SceneSampling,
                caption_settings: captions.CaptionSettings) -> str:
  """A hash of everything a sample's content depends on (not counts, shard sizes or paths)."""
  content = {
      "version": VERSION, "seed": settings.seed, "eval_seed": settings.eval_seed,
      "scenes": dataclasses.asdict(scene_sampling), "captions": dataclasses.asdict(caption_settings),
      "catalogue": [kind.source for kind in scene_sampling.catalogue()],
  }
  return hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()[:16]


def plan_shards(settings: DataSettings, shard_fingerprint: str) -> list[ShardSpec]:
  """Every shard of every split and kind, in order."""
  if settings.seed == settings.eval_seed:
    raise InputError("the eval split must have its own seed", field="default_model_data.eval_seed")
  specs = []
  for split in SPLITS:
    for kind in KINDS:
      total, per_shard = settings.count(split, kind), settings.per_shard(kind)
      if total < 0 or per_shard < 1:
        raise InputError(f"need {kind} >= 0 and per-shard >= 1, got {total}, {per_shard}",
                         field=f"default_model_data.{kind}")
      for index, first in enumerate(range(0, total, per_shard)):
        specs.append(ShardSpec(split, kind, index, first, min(per_shard, total - first),
                               settings.split_seed(split), shard_fingerprint))
  return specs


def sample_attributes(split: str, sample_index: int, catalogue) -> captions.Attributes | None:
  """The eval split's balanced attributes (None: drawn at random, as in train)."""
  if split != "eval":
    return None
  names, patterns = colors.COLORS, appearance.PATTERNS
  return captions.Attributes(kind=catalogue[sample_index % len(catalogue)].name,
                             color=names[sample_index % len(names)],
                             pattern=patterns[(sample_index // len(names)) % len(patterns)])


def make_shard_arrays(spec: ShardSpec, scene_sampling: scenes.SceneSampling,
                      caption_settings: captions.CaptionSettings) -> dict[str, np.ndarray]:
  """The stacked arrays of one shard (see the module docstring)."""
  catalogue = scene_sampling.catalogue()
  per_sample = []
  for sample_index in range(spec.first_sample, spec.first_sample + spec.samples):
    rng = np.random.default_rng([spec.seed, KIND_CODES[spec.kind], sample_index])
    sample = samples.make_sample(rng, scene_sampling, caption_settings, spec.kind == "sheets",
                                 sample_attributes(spec.split, sample_index, catalogue))
    per_sample.append(sample.arrays())
  arrays = {name: np.stack([sample[name] for sample in per_sample]) for name in per_sample[0]}
  arrays["sample_index"] = np.arange(spec.first_sample, spec.first_sample + spec.samples)
  arrays["shard_info"] = np.array(json.dumps(spec.info()))
  return arrays


def write_shard(directory: str | os.PathLike, spec: ShardSpec,
                scene_sampling: scenes.SceneSampling,
                caption_settings: captions.CaptionSettings) -> dict[str, Any]:
  """Makes and atomically writes one shard; returns its manifest entry (with timing)."""
  start = time.perf_counter()
  arrays = make_shard_arrays(spec, scene_sampling, caption_settings)
  path = Path(directory) / spec.relative_path
  with files.atomic_path(path) as temporary:
    np.savez_compressed(temporary, **arrays)
  return {**spec.info(), "path": spec.relative_path, "bytes": path.stat().st_size,
          "seconds": time.perf_counter() - start}


def read_shard_info(path: str | os.PathLike) -> dict[str, Any] | None:
  """A shard's `shard_info`, or None if the file is missing or unreadable."""
  try:
    with np.load(path, allow_pickle=False) as shard:
      return json.loads(str(shard["shard_info"]))
  except (OSError, KeyError, ValueError):
    return None


def read_shard(path: str | os.PathLike) -> dict[str, np.ndarray]:
  """Every array of a shard (see the module docstring)."""
  path = Path(path)
  if not path.is_file():
    raise InputError("shard not found", path)
  try:
    with np.load(path, allow_pickle=False) as shard:
      return {name: shard[name] for name in shard.files}
  except (OSError, ValueError) as error:
    raise InputError(f"not a readable shard ({error})", path) from None


def _finished(directory: Path, spec: ShardSpec, previous: dict[str, Any]) -> dict[str, Any] | None:
  """The manifest entry of a shard that already exists as planned, else None."""
  info = read_shard_info(directory / spec.relative_path)
  if info is None:
    return None
  if info["fingerprint"] != spec.fingerprint:
    raise InputError(f"{spec.relative_path} was made with other settings (fingerprint "
                     f"{info['fingerprint']}, now {spec.fingerprint}); use a new directory",
                     directory, "default_model_data.output_directory")
  if (info["first_sample"], info["samples"]) != (spec.first_sample, spec.samples):
    return None  # A shard size or count changed: remake it.
  entry = previous.get(spec.relative_path, {})
  return {**spec.info(), "path": spec.relative_path,
          "bytes": (directory / spec.relative_path).stat().st_size,
          "seconds": entry.get("seconds")}


def _manifest(settings, scene_sampling, caption_settings, shard_fingerprint, entries, complete,
              wall_seconds) -> dict[str, Any]:
  splits: dict[str, Any] = {}
  for split in SPLITS:
    for kind in KINDS:
      shards = [entries[path] for path in sorted(entries)
                if entries[path]["split"] == split and entries[path]["kind"] == kind]
      timed = [shard for shard in shards if shard["seconds"] is not None]
      splits.setdefault(split, {})[kind] = {
          "samples": sum(shard["samples"] for shard in shards),
          "planned_samples": settings.count(split, kind),
          "bytes": sum(shard["bytes"] for shard in shards),
          "samples_per_second": (sum(s["samples"] for s in timed) / sum(s["seconds"] for s in timed)
                                 if timed else None),
          "shards": shards,
      }
  return {
      "format": FORMAT, "version": VERSION, "complete": complete,
      "fingerprint": shard_fingerprint,
      "settings": {"data": dataclasses.asdict(settings),
                   "scenes": dataclasses.asdict(scene_sampling),
                   "captions": dataclasses.asdict(caption_settings)},
      "catalogue": [{"kind": kind.name, "nouns": kind.nouns, "source": kind.source}
                    for kind in scene_sampling.catalogue()],
      "image_size": scene_sampling.image_size,
      "views_per_sheet": scene_sampling.sheet_tiles + 1,
      "view_order": "sheets: the reference tiles in grid order skipping the slot, then the slot",
      "view_kinds": samples.VIEW_KINDS,
      "dilation_radii": scene_sampling.dilation_radii,
      "tokenizer": TOKENIZER_FOLDER,
      "bytes": sum(entry["bytes"] for entry in entries.values()),
      "shard_seconds": sum(entry["seconds"] or 0.0 for entry in entries.values()),
      "wall_seconds_this_run": wall_seconds,
      "splits": splits,
  }


def _previous_entries(manifest_path: Path) -> dict[str, dict[str, Any]]:
  """An earlier run's shard entries by path ({} without a manifest): the timings of the shards
  it made are kept when they are not made again."""
  previous = {}
  if manifest_path.is_file():
    for split in files.read_json(manifest_path).get("splits", {}).values():
      for kind in split.values():
        previous.update({shard["path"]: shard for shard in kind["shards"]})
  return previous


def _write_shards(directory: Path, todo: list[ShardSpec], scene_sampling: scenes.SceneSampling,
                  caption_settings: captions.CaptionSettings, workers: int, progress: bool,
                  record: Callable[[dict[str, Any]], None]) -> None:
  """Makes and writes the shards `todo` in this process (workers <= 1) or in `workers`
  processes, calling `record` with each shard's manifest entry once it is written."""
  bar = tqdm.tqdm(total=len(todo), desc="default model data shards", unit="shard",
                  disable=not progress)
  if workers <= 1:
    for spec in todo:
      record(write_shard(directory, spec, scene_sampling, caption_settings))
      bar.update()
  else:
    # Fresh interpreters: forking a process that has initialised JAX is unsafe.
    context = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(workers, mp_context=context) as pool:
      futures = [pool.submit(write_shard, directory, spec, scene_sampling, caption_settings)
                 for spec in todo]
      for future in concurrent.futures.as_completed(futures):
        record(future.result())
        bar.update()
  bar.close()


def build_dataset(settings: DataSettings | None = None,
                  scene_sampling: scenes.SceneSampling | None = None,
                  caption_settings: captions.CaptionSettings | None = None, workers: int = 1,
                  progress: bool = True) -> dict[str, Any]:
  """Makes (or completes) the dataset in `settings.output_directory`; returns the manifest.

  Args:
    settings, scene_sampling, caption_settings: default: the gin-bound values.
    workers: processes making shards in parallel (1: this process).
    progress: show a progress bar.
  """
  settings = DataSettings() if settings is None else settings
  scene_sampling = scenes.SceneSampling() if scene_sampling is None else scene_sampling
  caption_settings = captions.CaptionSettings() if caption_settings is None else caption_settings
  if not settings.output_directory:
    raise InputError("no output directory given", field="default_model_data.output_directory")
  directory = Path(settings.output_directory)
  start = time.perf_counter()
  shard_fingerprint = fingerprint(settings, scene_sampling, caption_settings)
  specs = plan_shards(settings, shard_fingerprint)
  manifest_path = directory / MANIFEST_NAME
  previous = _previous_entries(manifest_path)
  entries = {}
  for spec in specs:
    entry = _finished(directory, spec, previous)
    if entry is not None:
      entries[spec.relative_path] = entry
  todo = [spec for spec in specs if spec.relative_path not in entries]

  word_tokenizer.WordTokenizer.from_words(captions.vocabulary(), settings.tokenizer_max_length
                                          ).save(directory / TOKENIZER_FOLDER)
  configs.save_gin_config(directory)
  manifest = lambda: _manifest(settings, scene_sampling, caption_settings, shard_fingerprint,
                               entries, len(entries) == len(specs), time.perf_counter() - start)

  def record(entry: dict[str, Any]) -> None:
    entries[entry["path"]] = entry
    files.write_json(manifest_path, manifest())

  _write_shards(directory, todo, scene_sampling, caption_settings, workers, progress, record)
  final = manifest()
  files.write_json(manifest_path, final)
  return final


def read_manifest(directory: str | os.PathLike) -> dict[str, Any]:
  """The manifest of a generated dataset; InputError if it is not one."""
  manifest = files.read_json(Path(directory) / MANIFEST_NAME)
  if manifest.get("format") != FORMAT:
    raise InputError(f"not a {FORMAT} manifest", Path(directory) / MANIFEST_NAME, "format")
  return manifest


def shard_paths(directory: str | os.PathLike, split: str, kind: str) -> list[Path]:
  """The shard files of one split and kind listed in the manifest, in order."""
  if split not in SPLITS or kind not in KINDS:
    raise InputError(f"split must be one of {SPLITS} and kind one of {KINDS}, got {split!r}, "
                     f"{kind!r}", field="split/kind")
  manifest = read_manifest(directory)
  return [Path(directory) / shard["path"] for shard in manifest["splits"][split][kind]["shards"]]


def iterate_batches(directory: str | os.PathLike, split: str, kind: str, batch_size: int,
                    seed: int, epochs: int | None = None) -> Iterator[dict[str, np.ndarray]]:
  """Shuffled batches of `batch_size` samples (every array of the shards but shard_info).

  Each epoch visits the shards in a random order and each shard's samples in a random order,
  carrying leftovers into the next shard; the last partial batch of an epoch is dropped.
  Deterministic in `seed`; endless when `epochs` is None.
  """
  paths = shard_paths(directory, split, kind)
  if not paths:
    raise InputError(f"no {split} {kind} in the dataset", Path(directory) / MANIFEST_NAME)
  rng = np.random.default_rng(seed)
  epoch = 0
  while epochs is None or epoch < epochs:
    pending: dict[str, np.ndarray] | None = None
    for shard_index in rng.permutation(len(paths)):
      shard = read_shard(paths[shard_index])
      del shard["shard_info"]
      order = rng.permutation(len(shard["sample_index"]))
      shard = {name: array[order] for name, array in shard.items()}
      if pending is not None:
        shard = {name: np.concatenate([pending[name], array]) for name, array in shard.items()}
      count = len(shard["sample_index"])
      for start in range(0, count - batch_size + 1, batch_size):
        yield {name: array[start:start + batch_size] for name, array in shard.items()}
      kept = count - count % batch_size
      pending = {name: array[kept:] for name, array in shard.items()}
    epoch += 1
