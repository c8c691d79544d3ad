"""What cropping tiles around the selection gains over whole downscaled frames.

The paper puts whole frames into the sheet and names the lost resolution as a limitation. For a
few camera/selection configurations this measures, per dataset view, how many tile pixels the
selection's mask covers when the tile is (a) the whole frame downscaled (letterboxed) and (b) a
crop around the selection's projected bounding box (signerf_jax.editing.crops), both resized to
the same tile size. The selection masks come from the geometry code itself: an axis-aligned box
(its visible silhouette) or a proxy mesh (its rendered hit mask).

  python experiments/measure_sheet_crops.py [--gin_param 'measure.tile_size = 512']

Writes measure_sheet_crops.json and .gin into --results DIR (default outputs/experiments/).
"""

from __future__ import annotations

import argparse

import gin
import jax.numpy as jnp
import numpy as np

from signerf_jax import camera
from signerf_jax import configs
from signerf_jax import files
from signerf_jax.editing import crops
from signerf_jax.geometry import mesh as mesh_lib
from signerf_jax.geometry import mesh_depth
from signerf_jax.geometry import primitives
from signerf_jax.geometry import selection

import machine  # experiments/machine.py (this script's directory is on sys.path)
import results_dir  # experiments/results_dir.py (this script's directory is on sys.path)


def orbit(num_views, distance, width, height, focal, elevation_degrees=30.0, arc_degrees=360.0,
          target=(0.0, 0.0, 0.0)):
  """Cameras on an arc around `target` (z up) looking at the scene origin."""
  angles = np.deg2rad(np.linspace(0, arc_degrees, num_views, endpoint=arc_degrees < 360))
  elevation = np.deg2rad(elevation_degrees)
  eyes = distance * np.stack([np.cos(elevation) * np.cos(angles),
                              np.cos(elevation) * np.sin(angles),
                              np.full_like(angles, np.sin(elevation))], -1)
  camera_to_world = camera.look_at(eyes.astype(np.float32), np.asarray(target, np.float32))
  return camera.Cameras.create(camera_to_world, fx=focal, width=width, height=height)


def selection_masks(cameras, selected):
  """[N, H, W] masks and [K, 3] points spanning the selection, for a Box or a proxy Mesh.

  A box gives its visible silhouette (no scene content in front of it); a mesh its hit mask.
  """
  if isinstance(selected, selection.Box):
    empty = jnp.zeros((cameras.num_cameras, cameras.height, cameras.width), jnp.float32)
    result = selection.shape_selection(cameras, selected, empty, empty, mask_mode="silhouette")
    return np.asarray(result.mask), np.asarray(selected.corners)
  return np.asarray(mesh_depth.render_mesh_depth(selected, cameras).hit), selected.vertices


def configurations():
  """(name, description, cameras, box or proxy mesh) for each measured setup."""
  blender_like = orbit(12, 4.0, 800, 800, 1111.0)
  llff_like = orbit(10, 5.0, 504, 378, 407.6, elevation_degrees=10.0, arc_degrees=40.0)
  cow = mesh_lib.place_on_ground(primitives.primitive_cow(), (0.4, -0.3, 0.0), size=0.6)
  return [
      ("object_centric_large_box", "800x800 orbit at distance 4 (Blender-like), box 1.0 wide",
       blender_like, selection.Box.create([-0.5, -0.5, 0.0], [0.5, 0.5, 0.8])),
      ("object_centric_small_box", "800x800 orbit at distance 4, box 0.3 wide, off-centre",
       blender_like, selection.Box.create([0.5, 0.2, 0.0], [0.8, 0.5, 0.3])),
      ("forward_facing_off_centre",
       "504x378 cameras on a 40 degree arc (LLFF-like), box 0.6 wide, off-centre", llff_like,
       selection.Box.create([0.3, 0.8, 0.0], [0.9, 1.4, 0.6])),
      ("proxy_cow", "800x800 orbit at distance 4, primitive cow proxy 0.6 long", blender_like,
       cow),
  ]


def tile_mask_pixels(masks, boxes, tile_size):
  tiles = crops.crop_to_tiles(jnp.asarray(masks, jnp.float32)[..., None], boxes, tile_size,
                              tile_size, fill_value=0.0)
  return np.asarray(jnp.sum(tiles[..., 0] > 0.5, axis=(1, 2)))


@gin.configurable
def measure(tile_size: int = 256, margin: float = 0.15, max_upscale: float = 2.0):
  results = {"tile_size": tile_size, "margin": margin, "max_upscale": max_upscale,
             "configurations": {}}
  for name, description, cameras, selected in configurations():
    masks, points = selection_masks(cameras, selected)
    visible = masks.reshape(len(masks), -1).sum(axis=1) > 0
    full = crops.full_frame_boxes(cameras.num_cameras, cameras.height, cameras.width, tile_size,
                                  tile_size)
    cropped = crops.selection_crop_boxes(cameras, jnp.asarray(points, jnp.float32), tile_size,
                                         tile_size, margin=margin, max_upscale=max_upscale)
    full_pixels = tile_mask_pixels(masks, full, tile_size)[visible]
    crop_pixels = tile_mask_pixels(masks, cropped, tile_size)[visible]
    source_pixels = masks.reshape(len(masks), -1).sum(axis=1)[visible]
    results["configurations"][name] = {
        "description": description,
        "image_size": [cameras.width, cameras.height],
        "views_with_selection": int(visible.sum()),
        "selection_pixels_full_resolution_median": float(np.median(source_pixels)),
        "selection_pixels_per_tile_full_frame_median": float(np.median(full_pixels)),
        "selection_pixels_per_tile_crop_median": float(np.median(crop_pixels)),
        "selection_fraction_of_tile_full_frame_median": float(np.median(full_pixels))
                                                        / tile_size**2,
        "selection_fraction_of_tile_crop_median": float(np.median(crop_pixels)) / tile_size**2,
        "gain_crop_over_full_frame_median": float(np.median(crop_pixels / np.maximum(full_pixels,
                                                                                      1))),
    }
  return results


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  configs.add_gin_arguments(parser)
  results_dir.add_argument(parser)
  args = parser.parse_args()
  configs.parse_gin(args.gin_file, args.gin_param)
  result = {"machine": machine.record(), **measure()}
  files.write_json(args.results / "measure_sheet_crops.json", result)
  files.write_text(args.results / "measure_sheet_crops.gin", gin.operative_config_str())
  for name, numbers in result["configurations"].items():
    print(f"{name}: {numbers['selection_pixels_per_tile_full_frame_median']:.0f} -> "
          f"{numbers['selection_pixels_per_tile_crop_median']:.0f} selection pixels per "
          f"{result['tile_size']}^2 tile (x{numbers['gain_crop_over_full_frame_median']:.1f})")
  print(f"-> {args.results / 'measure_sheet_crops.json'}")


if __name__ == "__main__":
  main()
