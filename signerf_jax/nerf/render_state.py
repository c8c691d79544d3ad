"""What rendering a trained model computes once per model and variables, not per chunk: the
variables on the device, the occupancy sampler's short march and occupied cells, and a grid of
the proposal networks' densities that lets rendering skip their samples in empty space.

Each is kept for the last (model, variables) it was computed for (the variables' arrays are
held, so that `is` cannot match a new array at a recycled address): every view of a call and
every viewer frame would otherwise repeat it.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from signerf_jax.nerf import occupancy, ray_samples

# Cells per side of the proposal networks' density grid (at most: no finer than the networks'
# finest grid level). 128^3 cells take about a second to fill on a 2-core CPU.
PROPOSAL_GRID_RESOLUTION = 128
# Grid points evaluated at once while filling it (bounds the memory of the hash encoding).
GRID_POINTS_AT_ONCE = 1 << 17

# Entries kept per kind: a viewer alternates between two models (its moving frames take fewer
# field samples, `viewer.progressive`), which one entry would have recompute everything.
CACHE_ENTRIES = 4

_last: dict[str, list] = {}


def _cached(name: str, model, variables, compute: Callable[[], Any]):
  """compute(), or what it returned for the same model and variables lately. The model's
  `render_sample_fraction` changes none of these, so it is left out of the comparison."""
  key = dataclasses.replace(model, capacity=dataclasses.replace(model.capacity,
                                                                render_sample_fraction=1.0))
  leaves = jax.tree.leaves(variables)
  entries = _last.setdefault(name, [])
  for entry in entries:
    if entry[0] == key and len(entry[1]) == len(leaves) and all(
        old is new for old, new in zip(entry[1], leaves)):
      return entry[2]
  value = compute()
  entries[:] = [(key, leaves, value)] + entries[:CACHE_ENTRIES - 1]
  return value


def on_device(model, variables):
  """`variables` with every leaf a device array: a checkpoint loads as numpy arrays, which
  every chunk would otherwise copy to the device again (7% of a stitch chunk on a CPU)."""
  leaves, structure = jax.tree.flatten(variables)
  if all(isinstance(leaf, jax.Array) for leaf in leaves):
    return variables
  copied = _cached("on_device", model, variables, lambda: jax.device_put(variables))
  return jax.tree.unflatten(structure, jax.tree.leaves(copied))


def occupied_march(model, variables) -> ray_samples.OccupiedMarch | None:
  """`ray_samples.render_march` (tens of milliseconds of host work for a large grid)."""
  return _cached("march", model, variables,
                 lambda: ray_samples.render_march(model, variables))


def skipping(model, variables) -> dict[str, jax.Array]:
  """What `front_to_back.render_rays` skips empty space by: {"occupied": [R, R, R] bool} for
  the occupancy sampler (the cells its samples are evaluated in, found once rather than per
  chunk: a tenth of an empty chunk), {"proposal": [P, G, G, G] float32} for the proposal
  sampler (`proposal_grids`)."""
  if model.capacity.sampler == "occupancy":
    return _cached("skipping", model, variables, lambda: {"occupied": _occupied_cells(
        model.march_step, jnp.asarray(variables["occupancy"]))})
  resolution = min(PROPOSAL_GRID_RESOLUTION, model.capacity.proposal_finest_resolution)
  return _cached("skipping", model, variables, lambda: {"proposal": proposal_grids(
      model, on_device(model, variables)["params"], resolution)})


@functools.partial(jax.jit, static_argnums=0)
def _occupied_cells(step: float, grid):
  return occupancy.occupied_cells(grid, step, ray_samples.OCCUPANCY_MIN_ALPHA)


@functools.partial(jax.jit, static_argnums=(0, 2))
def proposal_grids(model, params, resolution: int):
  """Per proposal network, an upper estimate of its density in each cell of a grid over the
  unit cube (contracted or warped space, `NerfModel.to_unit_cube`).

  A cell holds the largest density at its 8 corners and its centre, and then the largest of
  its 3 x 3 x 3 neighbourhood, so that a density peak between the points evaluated is still
  seen by the cells around it.

  Returns:
    [P, resolution, resolution, resolution] float32 densities (1 / scene units).
  """
  corners = _lattice(resolution + 1) / resolution
  centres = (_lattice(resolution) + 0.5) / resolution
  grids = []
  for index, network in enumerate(model.proposal_fields):
    density = functools.partial(_densities, network, {"params": params[f"proposal_{index}"]})
    at_corners = density(corners).reshape((resolution + 1,) * 3)
    cells = density(centres).reshape((resolution,) * 3)
    for corner in np.ndindex(2, 2, 2):
      cells = jnp.maximum(cells, at_corners[corner[0]:corner[0] + resolution,
                                            corner[1]:corner[1] + resolution,
                                            corner[2]:corner[2] + resolution])
    grids.append(jax.lax.reduce_window(cells, -jnp.inf, jax.lax.max, (3, 3, 3), (1, 1, 1),
                                       "SAME"))
  return jnp.stack(grids)


def _lattice(size: int):
  """[size^3, 3] float32 integer points 0..size-1 per axis, x slowest (`occupancy.lookup`),
  computed in the program (as a constant it would be compiled into it)."""
  axis = jnp.arange(size, dtype=jnp.float32)
  return jnp.stack(jnp.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)


def _densities(network, variables, points):
  """The network's densities [P] at unit-cube points [P, 3], GRID_POINTS_AT_ONCE at a time."""
  count = points.shape[0]
  padded = int(np.ceil(count / GRID_POINTS_AT_ONCE)) * GRID_POINTS_AT_ONCE
  batches = jnp.pad(points, ((0, padded - count), (0, 0))).reshape(-1, GRID_POINTS_AT_ONCE, 3)
  return jax.lax.map(lambda batch: network.apply(variables, batch), batches).reshape(-1)[:count]
