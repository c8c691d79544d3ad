"""Mesh depth speed and accuracy: the JAX renderer against trimesh ray casting (and Embree).

Renders the spot cow (5,856 triangles) at 512 x 512 from cameras orbiting it and reports views
per second for
  * signerf_jax.geometry.mesh_depth.render_mesh_depth (jitted; compile time reported apart),
  * trimesh's exact ray casting (trimesh.ray.ray_triangle, float64, rtree candidates),
  * trimesh with Embree (trimesh.ray.ray_pyembree) when the optional `embreex` package is
    installed (it is not a dependency of signerf-jax),
side by side in one run, plus the depth error of the JAX renderer against trimesh.

  python experiments/bench_mesh_depth.py [--gin_param 'benchmark.num_views = 4']

Writes bench_mesh_depth.json and .gin (the full configuration) into --results DIR (default
outputs/experiments/).
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import gin
import jax
import numpy as np
import trimesh
from trimesh.ray import ray_triangle

from signerf_jax import camera
from signerf_jax import configs
from signerf_jax import files
from signerf_jax.errors import InputError
from signerf_jax.geometry import mesh as mesh_lib
from signerf_jax.geometry import mesh_depth

import machine  # experiments/machine.py (this script's directory is on sys.path)
import results_dir  # experiments/results_dir.py (this script's directory is on sys.path)

REPOSITORY = Path(__file__).resolve().parent.parent
DEFAULT_MESH = REPOSITORY.parent / "shared" / "data" / "meshes" / "spot" / "spot_triangulated.obj"


def orbit_cameras(mesh: mesh_lib.Mesh, num_views: int, size: int) -> camera.Cameras:
  """Cameras around the mesh (+y up), the mesh filling most of the frame."""
  lower, upper = mesh.bounds
  center = (lower + upper) / 2
  radius = float(np.linalg.norm(upper - lower)) / 2
  angles = np.linspace(0, 2 * np.pi, num_views, endpoint=False)
  eyes = center + 2.2 * radius * np.stack(
      [np.sin(angles), 0.35 + 0.15 * np.cos(2 * angles), np.cos(angles)], -1)
  camera_to_world = camera.look_at(eyes.astype(np.float32), center.astype(np.float32),
                                   up=(0.0, 1.0, 0.0))
  return camera.Cameras.create(camera_to_world, fx=1.1 * size, width=size, height=size)


def pixel_rays(cameras: camera.Cameras, index: int):
  rays = camera.image_rays(cameras, index)
  return (np.asarray(rays.origins, np.float64).reshape(-1, 3),
          np.asarray(rays.directions, np.float64).reshape(-1, 3))


def trimesh_distances(intersector, cameras: camera.Cameras, num_views: int,
                      chunk: int = 16384):
  """Ray distance per pixel for the first `num_views` cameras, and seconds per view.

  Rays go in chunks: trimesh's rtree candidate lists for a whole 512 x 512 view exhaust memory.
  """
  distances, seconds = [], 0.0
  for index in range(num_views):
    origins, directions = pixel_rays(cameras, index)
    distance = np.full(len(origins), np.inf)
    for begin in range(0, len(origins), chunk):
      part = slice(begin, begin + chunk)
      start = time.perf_counter()
      locations, ray_index, _ = intersector.intersects_location(origins[part], directions[part],
                                                                multiple_hits=False)
      seconds += time.perf_counter() - start
      if len(ray_index):  # trimesh returns locations of shape (0,) when nothing is hit
        distance[begin + ray_index] = np.linalg.norm(locations - origins[part][ray_index],
                                                     axis=-1)
    distances.append(distance.reshape(cameras.height, cameras.width))
  return np.stack(distances), seconds / num_views


def depth_error(distance: np.ndarray, reference: np.ndarray) -> dict[str, float]:
  both = np.isfinite(distance) & np.isfinite(reference)
  relative = np.abs(distance[both] - reference[both]) / reference[both]
  return {
      "hit_mask_disagreement_pixels": int(np.sum(np.isfinite(distance) != np.isfinite(reference))),
      "hit_pixels": int(np.isfinite(reference).sum()),
      "max_relative_depth_error": float(relative.max()),
      "pixels_over_1e-4_relative": int(np.sum(relative > 1e-4)),
  }


@gin.configurable
def benchmark(mesh_path: str = str(DEFAULT_MESH), num_views: int = 8, size: int = 512,
              tile_size: int = 4, trimesh_views: int = 2, repeats: int = 3):
  """Runs the comparison; returns the JSON-ready result."""
  mesh = mesh_lib.load_mesh(mesh_path)
  cameras = orbit_cameras(mesh, num_views, size)
  result = {
      "mesh": os.path.relpath(mesh_path, REPOSITORY),
      "triangles": int(mesh.faces.shape[0]),
      "image_size": [size, size],
      "views": num_views,
      "machine": {"cpus": os.cpu_count(), "processor": platform.processor(),
                  "jax": jax.__version__, "trimesh": trimesh.__version__},
  }

  start = time.perf_counter()
  depth = mesh_depth.render_mesh_depth(mesh, cameras, tile_size)
  jax.block_until_ready(depth)
  first_call = time.perf_counter() - start
  timings = []
  for _ in range(repeats):
    start = time.perf_counter()
    depth = mesh_depth.render_mesh_depth(mesh, cameras, tile_size)
    jax.block_until_ready(depth)
    timings.append(time.perf_counter() - start)
  seconds_per_view = min(timings) / num_views
  result["jax"] = {"tile_size": tile_size, "seconds_per_view": seconds_per_view,
                   "views_per_second": 1 / seconds_per_view,
                   "first_call_seconds_including_compile": first_call}
  jax_distance = np.asarray(depth.distance)

  reference, trimesh_seconds = trimesh_distances(ray_triangle.RayMeshIntersector(mesh.to_trimesh()),
                                                 cameras, trimesh_views)
  result["trimesh"] = {"seconds_per_view": trimesh_seconds, "views_per_second": 1 / trimesh_seconds,
                       "views_timed": trimesh_views}
  result["jax_vs_trimesh_error"] = depth_error(jax_distance[:trimesh_views], reference)
  result["speedup_jax_over_trimesh"] = trimesh_seconds / seconds_per_view

  if trimesh.ray.has_embree:
    from trimesh.ray import ray_pyembree  # pylint: disable=g-import-not-at-top  (optional)

    embree_distance, embree_seconds = trimesh_distances(
        ray_pyembree.RayMeshIntersector(mesh.to_trimesh()), cameras, num_views)
    result["trimesh_embree"] = {"seconds_per_view": embree_seconds,
                                "views_per_second": 1 / embree_seconds}
    result["embree_vs_trimesh_error"] = depth_error(embree_distance[:trimesh_views], reference)
    result["speedup_jax_over_embree"] = embree_seconds / seconds_per_view
  else:
    result["trimesh_embree"] = {"available": False,
                                "reason": "embreex is not installed (pip install embreex)"}
  return result


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  configs.add_gin_arguments(parser)
  results_dir.add_argument(parser)
  args = parser.parse_args()
  configs.parse_gin(args.gin_file, args.gin_param)
  measured_on = machine.record()
  try:
    result = {"machine": measured_on, **benchmark()}
  except InputError as error:  # e.g. the shared data is absent
    raise SystemExit(f"bench_mesh_depth: {error} (set benchmark.mesh_path)") from None
  files.write_json(args.results / "bench_mesh_depth.json", result)
  files.write_text(args.results / "bench_mesh_depth.gin", gin.operative_config_str())
  print(f"jax {result['jax']['views_per_second']:.2f} views/s, trimesh "
        f"{result['trimesh']['views_per_second']:.3f} views/s "
        f"(x{result['speedup_jax_over_trimesh']:.0f}), embree "
        f"{result['trimesh_embree'].get('views_per_second', float('nan')):.2f} views/s; "
        f"max relative depth error {result['jax_vs_trimesh_error']['max_relative_depth_error']:.1e}"
        f" -> {args.results / 'bench_mesh_depth.json'}")


if __name__ == "__main__":
  main()
