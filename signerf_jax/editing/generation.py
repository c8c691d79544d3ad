"""The diffusion side of an edit: a loaded generator sharded over devices, sheet recipes, and the
reference sheet with its per-tile re-roll (paper, steps 5 and "Reference Sheet").

`Generator` wraps a diffusers ControlNet inpainting pipeline (`diffusion.pipeline`) with the
edit's prompt embeddings and generation options. Every call inpaints one batch of exactly
`batch_size = views_per_device * devices` samples, sharded along a "views" mesh axis
(`jax.sharding.NamedSharding`), with the networks replicated; shorter inputs are padded by
repeating their last sample. Sheets, re-rolls and the image set update all go through it, so
with one sheet size they share one compiled program.

Randomness: the sample drawn for key `k` depends only on `k` (`sampler.draw_noise`), so a sheet
or a view comes out the same whatever batch, device count or resumed run it is part of.
  * a sheet (or re-roll) with seed s uses `seed_key(s)`;
  * dataset view i of the update with edit seed s uses `view_key(s, i)`.

A sheet recipe names a sheet: "3" is the sheet generated with seed 3; "3/1,4@7" is that sheet with
tiles 1 and 4 regenerated with seed 7 while every other tile stays as it was (only those tiles
are masked, the rest of the sheet is context, and the result keeps the other tiles pixel for
pixel); steps chain: "3/1,4@7/0@2".
"""

from __future__ import annotations

import dataclasses
import re
import warnings
from pathlib import Path
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from signerf_jax import files, parallel, validation
from signerf_jax.diffusion import pipeline as pipeline_lib
from signerf_jax.diffusion import pipeline_components
from signerf_jax.diffusion.attention import AttentionOptions
from signerf_jax.editing import sheet as sheet_lib
from signerf_jax.errors import InputError
from signerf_jax.validation import NonNegativeFloat

MESH_AXIS = "views"
# A model's own mask growth in its model_index.json (`recommended_mask_dilation`; the shipped
# model's, and why, in default_model/export.py), and the growth of a model that paints 512 px
# tiles and does not say.
MASK_DILATION_KEY = "_signerf_mask_dilation_radius"
DEFAULT_MASK_DILATION = 24.0
# Instructions that multiply bf16 natively, as /proc/cpuinfo names them (x86 AVX512_BF16 and AMX,
# Arm BF16): without them XLA's bf16 matmuls take longer than fp32 ones, so bf16 sampling is
# slower (docs/performance.md).
BF16_CPU_FLAGS = frozenset({"avx512_bf16", "amx_bf16", "bf16"})
CPUINFO = Path("/proc/cpuinfo")
_RECIPE = re.compile(r"^\d+(/\d+(,\d+)*@\d+)*$")


def seed_key(seed: int) -> np.ndarray:
  """[2] uint32 key data of a sheet seed."""
  return np.asarray(jax.random.PRNGKey(seed))


def view_key(seed: int, view_index: int) -> np.ndarray:
  """[2] uint32 key data of dataset view `view_index` in the update with edit seed `seed`."""
  return np.asarray(jax.random.fold_in(jax.random.PRNGKey(seed), view_index))


@dataclasses.dataclass(frozen=True, eq=False)
class Generator:
  """A pipeline with its prompt and options, generating fixed-size sharded batches.

  Attributes:
    pipeline: the loaded pipeline, parameters replicated over `mesh`.
    prompt: the encoded prompt (one row, broadcast to the batch).
    options: the generation knobs (steps, strength, guidance, ControlNet scale, ...).
    mesh: the devices, axis "views".
    views_per_device: samples each device inpaints per call.
    winograd_convolutions: False for calls made once (quicker to compile, slower to run;
      `pipeline.generate`).
  """

  pipeline: pipeline_lib.Pipeline
  prompt: object
  options: pipeline_lib.GenerationOptions
  mesh: Mesh
  views_per_device: int
  winograd_convolutions: bool = True

  @property
  def batch_size(self) -> int:
    return self.views_per_device * self.mesh.size

  @property
  def latent_factor(self) -> int:
    return self.pipeline.models.latent_factor

  def shard(self, array, dtype=jnp.float32) -> jax.Array:
    """`array` ([n, ...], n <= batch_size) padded to `batch_size` rows by repeating its last
    row and sharded along "views"."""
    array = jnp.asarray(array, dtype)
    if not 0 < len(array) <= self.batch_size:
      raise ValueError(f"a batch holds 1 to {self.batch_size} samples, got {len(array)}")
    padding = self.batch_size - len(array)
    if padding:
      array = jnp.concatenate([array, jnp.repeat(array[-1:], padding, axis=0)])
    return jax.device_put(array, parallel.batch_sharded(self.mesh))

  def __call__(self, image, mask, control, keys) -> np.ndarray:
    """Inpaints up to `batch_size` samples in one compiled, sharded call.

    Args:
      image: [n, H, W, 3] in [0, 1]; mask: [n, H, W, 1] in [0, 1] (>= 0.5 regenerated);
      control: [n, H, W, C] in [0, 1]: n samples, or already padded to `batch_size`.
      keys: [n, 2] uint32 key data, one per sample.
    Returns:
      [n, H, W, 3] float32 in [0, 1].
    """
    output = self.dispatch(image, mask, control, keys)
    return np.asarray(jax.device_get(output))[:len(keys)]

  def dispatch(self, image, mask, control, keys, control_embedding=None) -> jax.Array:
    """`__call__`'s generation, returned as soon as it is dispatched (JAX computes it
    asynchronously; reading the array waits), padded: [batch_size, H, W, 3] sharded along
    "views", row i < n the sample of keys[i]; `control_embedding` ([n, H / f, W / f, E]), the
    control's `control_embedding` when computed already. The sampler is always given it
    (computed here when not), so that every call of one size runs one compiled sampler."""
    control = self.shard(control)
    if control_embedding is None:
      control_embedding = self.control_embedding(control)
    return pipeline_lib.generate(
        self.pipeline, self.prompt, self.shard(image), self.shard(mask), control,
        key=self.shard(keys, jnp.uint32), options=self.options,
        winograd_convolutions=self.winograd_convolutions,
        control_embedding=self.shard(control_embedding))

  def control_embedding(self, control, base=None, region=None) -> jax.Array:
    """The ControlNet's embedding of control images [n, H, W, C] (`pipeline.control_embedding`,
    rounding as this generator's sampler would): [n, H / f, W / f, E]; with `base` (the
    embedding [1 or n, ...] of controls equal to `control` outside the pixel rectangle
    `region`, (top, left, height, width)), only the cells the rectangle reaches are computed."""
    return pipeline_lib.control_embedding(
        self.pipeline.models, control, base, region,
        winograd_convolutions=self.winograd_convolutions)


def cpu_lacks_bf16_instructions() -> bool:
  """Whether JAX computes on a CPU that `CPUINFO` shows without any of `BF16_CPU_FLAGS`
  (False on accelerators, and where there is no such file to tell)."""
  if jax.default_backend() != "cpu" or not CPUINFO.is_file():
    return False
  return not BF16_CPU_FLAGS & set(CPUINFO.read_text(errors="replace").split())


def load_generator(model: str, controlnet: str, scheduler_kind: str, prompt: str,
                   negative_prompt: str, options: pipeline_lib.GenerationOptions,
                   views_per_device: int, attention: AttentionOptions = AttentionOptions(),
                   mesh: Mesh | None = None, precision: str = "float32") -> Generator:
  """Loads a diffusers ControlNet inpainting pipeline (and an optional separate ControlNet);
  `attention` says how its models evaluate attention, `precision` ("float32" or "bfloat16") the
  dtype its weights are stored and its matmuls and convolutions computed in."""
  if not Path(model).is_dir():
    raise InputError("diffusion model directory not found (pass --model, a diffusers "
                     "inpainting pipeline)", model, "model")
  if views_per_device < 1:
    raise InputError(f"must be at least 1, got {views_per_device}",
                     field="UpdateConfig.views_per_device")
  dtype = jnp.dtype(precision)
  if dtype == jnp.bfloat16 and cpu_lacks_bf16_instructions():
    warnings.warn("EditConfig.diffusion_precision = 'bfloat16' on a CPU without bf16 "
                  f"instructions (none of {sorted(BF16_CPU_FLAGS)} in {CPUINFO}): sampling is "
                  "slower than in float32 there (docs/performance.md)", stacklevel=2)
  pipeline = pipeline_lib.load_pipeline(model, controlnet=controlnet or None,
                                        scheduler_kind=scheduler_kind or None,
                                        dtype=dtype, compute_dtype=dtype, attention=attention)
  if pipeline.models.controlnet is None:
    raise InputError("the pipeline has no ControlNet: SIGNeRF conditions on depth (pass "
                     "--controlnet)", model, "controlnet")
  mesh = parallel.device_mesh(axis_name=MESH_AXIS) if mesh is None else mesh
  pipeline = dataclasses.replace(pipeline, models=parallel.replicate(pipeline.models, mesh))
  # With the unconditional embeddings too, so that options with or without guidance can share
  # this generator (`dataclasses.replace(generator, options=...)`).
  embeddings = pipeline_lib.encode_prompts(pipeline, [prompt], negative_prompt or None)
  return Generator(pipeline, parallel.replicate(embeddings, mesh), options, mesh,
                   views_per_device)


def native_tile_size(model: str | Path) -> int:
  """The model's training resolution in pixels: its UNet's `sample_size` (latents) times the
  VAE's latent factor, read from the configs (64 for the shipped model, 512 for SD 1.5)."""
  unet_path = Path(model) / "unet" / "config.json"
  vae_path = Path(model) / "vae" / "config.json"
  sample_size = files.read_json(unet_path).get("sample_size")
  if isinstance(sample_size, (list, tuple)):
    sample_size = min(sample_size)
  if not isinstance(sample_size, int) or sample_size < 1:
    raise InputError("the UNet config has no sample_size; set SheetConfig.tile_size", unet_path,
                     "sample_size")
  blocks = files.read_json(vae_path).get("block_out_channels")
  if not isinstance(blocks, list) or not blocks:
    raise InputError("the VAE config has no block_out_channels", vae_path, "block_out_channels")
  return sample_size * 2**(len(blocks) - 1)


def recommended_mask_dilation(model: str | Path) -> float:
  """The mask growth (`SelectionConfig.dilation_radius`, pixels at 512) edits with this model
  use unless told otherwise: the `MASK_DILATION_KEY` entry of its `model_index.json` (diffusers
  ignores keys starting with "_"), else `DEFAULT_MASK_DILATION` (an SD-sized model)."""
  index_path = Path(model) / pipeline_components.MODEL_INDEX
  if not index_path.is_file():
    return DEFAULT_MASK_DILATION
  radius = files.read_json(index_path).get(MASK_DILATION_KEY, DEFAULT_MASK_DILATION)
  return float(validation.check_value(radius, NonNegativeFloat, index_path, MASK_DILATION_KEY))


# ------------------------------------------------------------------------------------------------
# Sheet recipes.


@dataclasses.dataclass(frozen=True)
class SheetRecipe:
  """A sheet: the seed it was generated with, then re-rolls (tiles, seed) applied in order."""

  seed: int
  rerolls: tuple[tuple[tuple[int, ...], int], ...] = ()

  @classmethod
  def parse(cls, text: str) -> "SheetRecipe":
    text = str(text).replace(" ", "")
    if not _RECIPE.match(text):
      raise InputError(f"not a sheet recipe: {text!r} (expected SEED or SEED/TILE,TILE@SEED...)",
                       field="sheet")
    seed, *steps = text.split("/")
    rerolls = []
    for step in steps:
      tiles, reroll_seed = step.split("@")
      rerolls.append((tuple(sorted({int(tile) for tile in tiles.split(",")})), int(reroll_seed)))
    return cls(int(seed), tuple(rerolls))

  def __str__(self) -> str:
    steps = "".join(f"/{','.join(map(str, tiles))}@{seed}" for tiles, seed in self.rerolls)
    return f"{self.seed}{steps}"

  @property
  def parent(self) -> "SheetRecipe | None":
    return SheetRecipe(self.seed, self.rerolls[:-1]) if self.rerolls else None

  @property
  def file_stem(self) -> str:
    return str(self).replace("/", "_r").replace(",", "-").replace("@", "s")

  def check(self, num_tiles: int) -> None:
    for tiles, _ in self.rerolls:
      if max(tiles) >= num_tiles:
        raise InputError(f"recipe {self} re-rolls tile {max(tiles)} but the sheet has tiles "
                         f"0..{num_tiles - 1}", field="sheet")


@dataclasses.dataclass(frozen=True)
class SheetInputs:
  """The reference sheet's inputs, [SH, SW, C] each, and the reference tiles they hold.

  Attributes:
    rgb: [SH, SW, 3] reference renders (slot: grey); control: [SH, SW, 1]; mask: [SH, SW, 1].
    layout: the sheet layout.
  """

  rgb: np.ndarray
  control: np.ndarray
  mask: np.ndarray
  layout: sheet_lib.SheetLayout

  @classmethod
  def from_tiles(cls, rgb, control, mask, layout: sheet_lib.SheetLayout) -> "SheetInputs":
    """From [M, h, w, 3] renders, [M, h, w] control and [M, h, w] masks."""
    sheets = sheet_lib.reference_sheet_inputs(jnp.asarray(rgb), jnp.asarray(control)[..., None],
                                              jnp.asarray(mask)[..., None], layout)
    return cls(*(np.asarray(array) for array in sheets), layout)

  def tile_cells(self, tiles: Sequence[int]) -> np.ndarray:
    """[SH, SW, 1] float32: 1 on the cells of `tiles`, 0 elsewhere."""
    layout = self.layout
    chosen = np.zeros((layout.num_tiles, layout.tile_height, layout.tile_width, 1), np.float32)
    chosen[list(tiles)] = 1.0
    empty_slot = np.zeros((layout.tile_height, layout.tile_width, 1), np.float32)
    return np.asarray(sheet_lib.assemble(chosen, empty_slot, layout, is_mask=True))


def generate_sheets(generator: Generator, inputs: SheetInputs, recipes: Sequence[SheetRecipe],
                    known: Callable[[SheetRecipe], np.ndarray | None] = lambda recipe: None,
                    on_batch: Callable[[dict[SheetRecipe, np.ndarray]], None] = lambda made: None
                    ) -> dict[SheetRecipe, np.ndarray]:
  """The sheets of `recipes` ([SH, SW, 3] each), with those `known` returns reused.

  Plain seeds are generated together in batches; re-rolls of one parent with the same tiles
  are batched too; parents are made first. `on_batch` receives each batch's sheets as soon as
  they are made (recipe -> sheet; parents needed by re-rolls included).
  """
  for recipe in recipes:
    recipe.check(inputs.layout.num_tiles)
  sheets: dict[SheetRecipe, np.ndarray] = {}
  needed, frontier = set(), list(recipes)
  while frontier:
    recipe = frontier.pop()
    if recipe in needed:
      continue
    needed.add(recipe)
    stored = known(recipe)
    if stored is not None:
      sheets[recipe] = stored
    elif recipe.parent is not None:
      frontier.append(recipe.parent)
  depth = lambda recipe: len(recipe.rerolls)
  for level in range(max(map(depth, needed), default=-1) + 1):
    groups: dict[tuple, list[SheetRecipe]] = {}
    for recipe in sorted(needed - sheets.keys(), key=str):
      if depth(recipe) == level:
        groups.setdefault((recipe.parent, recipe.rerolls[-1][0] if level else ()), []
                          ).append(recipe)
    for (parent, tiles), members in groups.items():
      if parent is None:
        image, mask = inputs.rgb, inputs.mask
      else:
        cells = inputs.tile_cells(tiles)
        # The re-rolled tiles start again from the reference renders; the rest is context.
        image = np.where(cells > 0, inputs.rgb, sheets[parent])
        mask = inputs.mask * cells
      for start in range(0, len(members), generator.batch_size):
        chunk = members[start:start + generator.batch_size]
        seeds = [member.seed if parent is None else member.rerolls[-1][1] for member in chunk]
        batch = lambda array: np.repeat(array[None], len(chunk), axis=0)
        generated = generator(batch(image), batch(mask), batch(inputs.control),
                              np.stack([seed_key(seed) for seed in seeds]))
        for member, sheet in zip(chunk, generated):
          sheets[member] = sheet if parent is None else np.where(cells > 0, sheet,
                                                                 sheets[parent])
        on_batch({member: sheets[member] for member in chunk})
  return {recipe: sheets[recipe] for recipe in recipes}
