"""`signerf demo` makes the same scene and edit on every machine: nothing it reads comes from
outside the repository (../shared/data may or may not be there)."""

import dataclasses

import gin
import numpy as np
import pytest

from signerf_jax import configs
from signerf_jax.data import synthetic
from signerf_jax.editing import demo
from signerf_jax.geometry import masks


@pytest.fixture(autouse=True)
def clear_gin():
  yield
  gin.clear_config()


def _scene_json(settings: synthetic.SceneSettings) -> str:
  description = synthetic.make_scene(demo.DemoSettings().scene_seed, settings).describe()
  return repr({key: np.asarray(value).round(9).tolist() if isinstance(value, np.ndarray)
               else value for key, value in description.items()})


def test_the_demo_scene_is_the_one_a_machine_without_shared_meshes_makes(tmp_path):
  configs.parse_gin(["demo"])
  settings = configs.build(synthetic.SceneSettings)
  with_meshes = tmp_path / "meshes"
  with_meshes.mkdir()
  (with_meshes / "box.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n"
                                       "f 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n")
  empty = tmp_path / "empty"
  empty.mkdir()
  scenes = {_scene_json(dataclasses.replace(settings, mesh_directory=str(directory)))
            for directory in (empty, tmp_path / "absent")}
  assert scenes == {_scene_json(settings)}
  # A mesh directory would change the scene: the demo's settings must be what keeps it out.
  assert _scene_json(dataclasses.replace(settings, mesh_directory=str(with_meshes))) not in scenes
  assert all(shape.mesh_path is None for shape in synthetic.make_scene(0, settings).shapes)


def test_the_demo_proxy_is_the_primitive_cow(tmp_path):
  scene = {"free_spot": {"center": [0.2, -0.3, 0.0], "radius": 0.3}, "up": [0.0, 0.0, 1.0]}
  bindings = demo.edit_bindings(tmp_path / "scene", scene, demo.DemoSettings(), "a red cow",
                                str(tmp_path / "model"))
  assert "SelectionConfig.proxy = 'primitive:cow'" in bindings


def test_the_demo_masks_grow_the_proxy_silhouette_by_one_pixel_of_its_images():
  """At the demo's 64 px a wider mask lets the shipped model paint the cow larger than the proxy
  and differently from view to view: the retrained object becomes a fog (gin_configs/demo.gin
  has the measurements). The radius is given at 512 px (`geometry.masks.REFERENCE_SIZE`)."""
  configs.parse_gin(["demo"])
  size = gin.query_parameter("synthetic_cameras.image_size")
  point = np.zeros((size, size), bool)
  point[size // 2, size // 2] = True
  grown = masks.dilate_and_feather(point, radius=gin.query_parameter(
      "SelectionConfig.dilation_radius"))
  assert int(np.count_nonzero(grown)) == 5  # The pixel and its four neighbours: 1 px.
