"""The reference sheet: M tiles plus one empty slot in an R x C grid (paper, "Reference Sheet").

Layout: tiles are placed row by row, skipping the slot (default bottom-right). Each tile is
tile_height x tile_width; for the latent diffusion model every tile is padded at its bottom and
right edge up to a multiple of `LATENT_FACTOR` (8), so every tile starts on a latent cell and no
latent cell straddles two tiles. Padding repeats the tile's last row/column for images and
control maps and is 0 for masks (never inpainted); `disassemble` drops it again.

What the slot holds:
  * reference sheet generation: the slot is left empty, as in the paper: neutral grey colour
    (0.5), control 0 (= far, no structure) and mask 0, so the model has nothing to generate there
    and the slot does not pull the reference tiles towards any content;
  * image set update: the generated reference sheet stays fixed (mask 0 on every tile) and each
    dataset view goes into the slot with its own colour, control depth and mask; only the slot
    is inpainted (`slot_update_inputs`, vmapped over views).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from signerf_jax.errors import InputError

LATENT_FACTOR = 8
EMPTY_SLOT_COLOR = 0.5


@dataclasses.dataclass(frozen=True)
class SheetLayout:
  """Where the tiles and the empty slot go. Hashable, so it can be a static jit argument.

  Attributes:
    rows, columns: the grid; it holds rows * columns - 1 reference tiles.
    slot_row, slot_column: the empty slot's cell (negative values count from the end).
    tile_height, tile_width: tile content size in pixels.
  """

  rows: int = 2
  columns: int = 3
  slot_row: int = -1
  slot_column: int = -1
  tile_height: int = 256
  tile_width: int = 256

  def __post_init__(self):
    if self.rows < 1 or self.columns < 1 or self.rows * self.columns < 2:
      raise InputError(f"a {self.rows} x {self.columns} grid has no room for a tile and a slot",
                       field="sheet_layout")
    if not (-self.rows <= self.slot_row < self.rows
            and -self.columns <= self.slot_column < self.columns):
      raise InputError(f"slot ({self.slot_row}, {self.slot_column}) is outside the "
                       f"{self.rows} x {self.columns} grid", field="sheet_layout")
    if self.tile_height < 1 or self.tile_width < 1:
      raise InputError("tile size must be positive", field="sheet_layout")

  @property
  def num_tiles(self) -> int:
    """M, the reference tiles the sheet holds."""
    return self.rows * self.columns - 1

  @property
  def slot_index(self) -> int:
    """The slot's cell in row-major order."""
    return (self.slot_row % self.rows) * self.columns + self.slot_column % self.columns

  @property
  def padded_tile_shape(self) -> tuple[int, int]:
    """(height, width) of a tile's cell, rounded up to multiples of LATENT_FACTOR."""
    round_up = lambda size: -(-size // LATENT_FACTOR) * LATENT_FACTOR
    return round_up(self.tile_height), round_up(self.tile_width)

  @property
  def sheet_shape(self) -> tuple[int, int]:
    """(height, width) of the sheet, multiples of LATENT_FACTOR."""
    cell_height, cell_width = self.padded_tile_shape
    return self.rows * cell_height, self.columns * cell_width

  @property
  def slot_offset(self) -> tuple[int, int]:
    """(row, column) of the slot's top-left pixel in the sheet."""
    cell_height, cell_width = self.padded_tile_shape
    return ((self.slot_row % self.rows) * cell_height,
            (self.slot_column % self.columns) * cell_width)

  @property
  def slot_region(self) -> tuple[int, int, int, int]:
    """(top, left, height, width) in pixels of the slot's cell, padding included: all the
    image set update changes in a sheet's inputs."""
    return (*self.slot_offset, *self.padded_tile_shape)


def _pad_tiles(tiles: jax.Array, layout: SheetLayout, is_mask: bool) -> jax.Array:
  """[..., h, w, C] -> [..., cell_height, cell_width, C], padding bottom and right."""
  cell_height, cell_width = layout.padded_tile_shape
  widths = [(0, 0)] * (tiles.ndim - 3) + [(0, cell_height - layout.tile_height),
                                           (0, cell_width - layout.tile_width), (0, 0)]
  return jnp.pad(tiles, widths, mode="constant" if is_mask else "edge")


def _check_tiles(tiles, layout: SheetLayout, count: int, name: str) -> None:
  expected = (count, layout.tile_height, layout.tile_width)
  if tiles.ndim != 4 or tuple(tiles.shape[:3]) != expected:
    raise InputError(f"expected [{count}, {layout.tile_height}, {layout.tile_width}, C], got "
                     f"{list(tiles.shape)}", field=name)


@functools.partial(jax.jit, static_argnames=("layout", "is_mask"))
def assemble(tiles, slot, layout: SheetLayout, is_mask: bool = False) -> jax.Array:
  """Puts M tiles and the slot's content into one sheet.

  Args:
    tiles: [M, tile_height, tile_width, C] (M = layout.num_tiles), in grid order skipping the slot.
    slot: [tile_height, tile_width, C] the slot's content.
    layout: the sheet layout.
    is_mask: pad with 0 (masks) instead of repeating the edge (images, control).
  Returns:
    [sheet_height, sheet_width, C].
  """
  _check_tiles(tiles, layout, layout.num_tiles, "tiles")
  _check_tiles(slot[None], layout, 1, "slot")
  cells = jnp.insert(tiles, layout.slot_index, slot, axis=0)
  cells = _pad_tiles(cells, layout, is_mask)
  cell_height, cell_width = layout.padded_tile_shape
  grid = cells.reshape(layout.rows, layout.columns, cell_height, cell_width, -1)
  return jnp.swapaxes(grid, 1, 2).reshape(*layout.sheet_shape, -1)


@functools.partial(jax.jit, static_argnames=("layout",))
def disassemble(sheet, layout: SheetLayout):
  """Inverse of `assemble`: the M tiles and the slot, padding removed.

  Args:
    sheet: [sheet_height, sheet_width, C].
  Returns:
    tiles: [M, tile_height, tile_width, C]; slot: [tile_height, tile_width, C].
  """
  if tuple(sheet.shape[:2]) != layout.sheet_shape:
    raise InputError(f"sheet is {list(sheet.shape[:2])}, layout needs {list(layout.sheet_shape)}",
                     field="sheet")
  cell_height, cell_width = layout.padded_tile_shape
  grid = sheet.reshape(layout.rows, cell_height, layout.columns, cell_width, -1)
  cells = jnp.swapaxes(grid, 1, 2).reshape(layout.rows * layout.columns, cell_height, cell_width,
                                           -1)
  cells = cells[:, :layout.tile_height, :layout.tile_width]
  slot = cells[layout.slot_index]
  return jnp.delete(cells, layout.slot_index, axis=0, assume_unique_indices=True), slot


@functools.partial(jax.jit, static_argnames=("layout",))
def slot_tiles(sheets, layout: SheetLayout) -> jax.Array:
  """[B, SH, SW, C] sheets -> [B, tile_height, tile_width, C] their slots (`disassemble`)."""
  return jax.vmap(lambda sheet: disassemble(sheet, layout)[1])(sheets)


@functools.partial(jax.jit, static_argnames=("layout",))
def reference_sheet_inputs(rgb, control, mask, layout: SheetLayout):
  """The three sheets for reference sheet generation, with the slot left empty.

  Args:
    rgb: [M, h, w, 3] reference views in [0, 1].
    control: [M, h, w, Cc] normalised control depth (Cc = 1 or 3).
    mask: [M, h, w, 1] inpainting masks in [0, 1].
  Returns:
    (rgb [SH, SW, 3], control [SH, SW, Cc], mask [SH, SW, 1]); the slot is grey, control 0 and
    mask 0 (see the module docstring).
  """
  tile_shape = (layout.tile_height, layout.tile_width)
  empty = lambda channels, value: jnp.full(tile_shape + (channels,), value, jnp.float32)
  return (assemble(rgb, empty(rgb.shape[-1], EMPTY_SLOT_COLOR), layout),
          assemble(control, empty(control.shape[-1], 0.0), layout),
          assemble(mask, empty(mask.shape[-1], 0.0), layout, is_mask=True))


def _place_in_slot(sheet, tile, layout: SheetLayout, is_mask: bool):
  padded = _pad_tiles(tile, layout, is_mask).astype(sheet.dtype)
  return jax.lax.dynamic_update_slice(sheet, padded, (*layout.slot_offset, 0))


@functools.partial(jax.jit, static_argnames=("layout",))
def slot_update_inputs(sheet_rgb, sheet_control, view_rgb, view_control, view_mask,
                       layout: SheetLayout):
  """Diffusion inputs for the image set update: each view in the slot of the fixed sheet.

  Vmapped over the views; one compilation serves every batch of the same size.

  Args:
    sheet_rgb: [SH, SW, 3] the generated reference sheet.
    sheet_control: [SH, SW, Cc] the reference sheet's control.
    view_rgb: [B, h, w, 3] dataset views as tiles (`crops.crop_to_tiles`).
    view_control: [B, h, w, Cc] their normalised control depth.
    view_mask: [B, h, w, 1] their inpainting masks.
    layout: the sheet layout.
  Returns:
    (rgb [B, SH, SW, 3], control [B, SH, SW, Cc], mask [B, SH, SW, 1]): the mask is zero on
    every reference tile, so only the slot is inpainted.
  """
  empty_mask = jnp.zeros(layout.sheet_shape + (view_mask.shape[-1],), jnp.float32)

  def one_view(rgb, control, mask):
    return (_place_in_slot(sheet_rgb, rgb, layout, False),
            _place_in_slot(sheet_control, control, layout, False),
            _place_in_slot(empty_mask, mask, layout, True))

  return jax.vmap(one_view)(view_rgb, view_control, view_mask)
