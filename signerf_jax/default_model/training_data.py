"""The default model's data in memory, and the batches its training stages take.

A split of the generated dataset (`dataset_builder`) is loaded once into memory (about 1.2 GB of
uint8/float16 arrays for 4,000 sheets and 8,000 single views), with captions turned into token ids.
Each training step then draws its batch from `np.random.default_rng([seed, stage code, step])`,
so the batch of step s is the same whether training ran straight through or was resumed at s:
the data iterator's position is the step itself.

Batches (numpy, float32, images in [0, 1]):
  `vae_batch`        {"image": [B, H, W, 3], "object": [B, H, W, 1]}: views drawn from every
                     view of every sample, a share of them greyed out (0.5) under a random
                     inpainting mask, as the masked images and the empty slot the encoder will
                     see in the pipeline, and where their object is visible (1) or not (0);
  `diffusion_batch`  sheets (2 x 3 of 64-pixel tiles, a random `batches.SHEET_MODES` mode per
                     sheet) and single views, each with image, mask, control [.., 1], object
                     [.., 1] (the visible silhouettes) and the caption's token ids (the empty
                     prompt with the caption-dropout probability, for classifier-free
                     guidance). Mask kinds are drawn per sample.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import tqdm

from signerf_jax.clip import word_tokenizer
from signerf_jax.default_model import batches
from signerf_jax.default_model import dataset_builder
from signerf_jax.editing import sheet as sheet_lib
from signerf_jax.errors import InputError

STAGE_CODES = {"vae": 0, "unet": 1, "controlnet": 2}
# What training reads of a sample; evaluation keeps everything.
TRAINING_ARRAYS = ("rgb", "depth", "silhouette", "dilated_silhouettes", "boxes",
                   "control_near_far", "caption")
EMPTY_SLOT_GREY = sheet_lib.EMPTY_SLOT_COLOR


@dataclasses.dataclass(frozen=True)
class SplitData:
  """One split in memory.

  Attributes:
    sheets, singles: arrays of the shards stacked over all samples (shard layout, see
      `dataset_builder`), plus `ids` [S, max_length] int32, the tokenised captions.
    tokenizer: the dataset's word tokenizer.
    mask_kinds: `batches.mask_kinds` of the dataset's dilation radii.
    layout: the sheet layout of the sheet samples (slot last, as the views are stored).
  """

  sheets: dict[str, np.ndarray]
  singles: dict[str, np.ndarray]
  tokenizer: word_tokenizer.WordTokenizer
  mask_kinds: tuple[str, ...]
  layout: sheet_lib.SheetLayout

  @property
  def num_sheets(self) -> int:
    return len(self.sheets["rgb"])

  @property
  def num_singles(self) -> int:
    return len(self.singles["rgb"])


def _stack_shards(paths: list[Path], keep, description: str, progress: bool
                  ) -> dict[str, np.ndarray]:
  parts: dict[str, list[np.ndarray]] = {}
  for path in tqdm.tqdm(paths, desc=description, unit="shard", leave=False, disable=not progress):
    shard = dataset_builder.read_shard(path)
    for name in keep or [name for name in shard if name != "shard_info"]:
      parts.setdefault(name, []).append(shard[name])
  return {name: np.concatenate(arrays) for name, arrays in parts.items()}


def load_split(directory: str | os.PathLike, split: str = "train",
               keep: tuple[str, ...] | None = TRAINING_ARRAYS, progress: bool = True) -> SplitData:
  """Loads a split of the dataset in `directory` (`keep`: the arrays to keep; None: all)."""
  manifest = dataset_builder.read_manifest(directory)
  tokenizer = word_tokenizer.WordTokenizer.from_directory(
      Path(directory) / dataset_builder.TOKENIZER_FOLDER)
  kinds = {}
  for kind in dataset_builder.KINDS:
    paths = dataset_builder.shard_paths(directory, split, kind)
    if not paths:
      raise InputError(f"the dataset has no {split} {kind}", Path(directory) / "manifest.json")
    arrays = _stack_shards(paths, keep, f"loading {split} {kind}", progress)
    arrays["ids"] = tokenizer.tokenize([str(text) for text in arrays["caption"]])
    kinds[kind] = arrays
  size = manifest["image_size"]
  return SplitData(sheets=kinds["sheets"], singles=kinds["singles"], tokenizer=tokenizer,
                   mask_kinds=batches.mask_kinds(manifest["dilation_radii"]),
                   layout=sheet_lib.SheetLayout(rows=2, columns=3, tile_height=size,
                                                tile_width=size))


def step_rng(seed: int, stage: str, step: int) -> np.random.Generator:
  """The generator of one step's batch (independent of how training was split into runs)."""
  return np.random.default_rng([seed, STAGE_CODES[stage], step])


def _take(arrays: dict[str, np.ndarray], indices: np.ndarray) -> dict[str, np.ndarray]:
  return {name: array[indices] for name, array in arrays.items()}


def _probabilities(values, count: int, name: str) -> np.ndarray:
  values = np.asarray(values, np.float64)
  if values.shape != (count,) or np.any(values < 0) or values.sum() <= 0:
    raise InputError(f"expected {count} non-negative weights, got {values.tolist()}", field=name)
  return values / values.sum()


def vae_batch(data: SplitData, rng: np.random.Generator, batch_size: int,
              masked_fraction: float) -> dict[str, np.ndarray]:
  """{"image": [batch_size, H, W, 3] float32 views in [0, 1], "object": [batch_size, H, W, 1]
  float32 visible object pixels} (module docstring)."""
  views_per_sheet = data.sheets["rgb"].shape[1]
  sheet_views = data.num_sheets * views_per_sheet
  picks = rng.choice(sheet_views + data.num_singles, batch_size, replace=False)
  from_sheets, from_singles = picks[picks < sheet_views], picks[picks >= sheet_views] - sheet_views
  views = lambda name: np.concatenate([
      data.sheets[name][from_sheets // views_per_sheet, from_sheets % views_per_sheet],
      data.singles[name][from_singles, 0]])
  images = views("rgb").astype(np.float32) / 255.0
  view_arrays = {name: views(name)[:, None]
                 for name in ("silhouette", "dilated_silhouettes", "boxes")}
  kinds = rng.integers(len(data.mask_kinds), size=batch_size)
  masks = batches.inpainting_masks(view_arrays, kinds)[:, 0, ..., None]
  masks *= (rng.uniform(size=batch_size) < masked_fraction)[:, None, None, None]
  visible_object = (view_arrays["silhouette"][:, 0, ..., None] > 0) * (1 - masks)
  return {"image": images * (1 - masks) + EMPTY_SLOT_GREY * masks,
          "object": visible_object.astype(np.float32)}


def diffusion_batch(data: SplitData, rng: np.random.Generator, num_sheets: int, num_singles: int,
                    mask_kind_weights, sheet_mode_weights, caption_dropout: float
                    ) -> dict[str, dict[str, np.ndarray]]:
  """{"sheets": ..., "singles": ...}, each {image, mask, control, object, ids} (module
  docstring).

  Args:
    mask_kind_weights: one weight per `data.mask_kinds` entry.
    sheet_mode_weights: one weight per `batches.SHEET_MODES` entry.
    caption_dropout: probability of the empty prompt.
  """
  kind_probabilities = _probabilities(mask_kind_weights, len(data.mask_kinds), "mask_kind_weights")
  mode_probabilities = _probabilities(sheet_mode_weights, len(batches.SHEET_MODES),
                                      "sheet_mode_weights")
  empty_ids = data.tokenizer.tokenize([""])[0]
  result = {}
  for kind, arrays, count in (("sheets", data.sheets, num_sheets),
                              ("singles", data.singles, num_singles)):
    chosen = _take(arrays, rng.choice(len(arrays["rgb"]), count, replace=False))
    masks = batches.inpainting_masks(
        chosen, rng.choice(len(data.mask_kinds), count, p=kind_probabilities))
    if kind == "sheets":
      modes = rng.choice(len(batches.SHEET_MODES), count, p=mode_probabilities)
      by_mode = [batches.sheet_inputs(chosen, masks, data.layout, mode)
                 for mode in batches.SHEET_MODES]
      inputs = {name: np.stack([np.asarray(by_mode[mode][name][index])
                                for index, mode in enumerate(modes)])
                for name in ("image", "mask", "control", "object")}
    else:
      inputs = {name: np.asarray(value) for name, value in
                batches.single_view_inputs(chosen, masks).items() if name != "masked_image"}
    dropped = rng.uniform(size=count) < caption_dropout
    inputs["ids"] = np.where(dropped[:, None], empty_ids[None], chosen["ids"])
    result[kind] = inputs
  return result
