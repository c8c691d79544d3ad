"""One sample of the default model's data: an object in a small synthetic scene, rendered.

A sample is a random scene (`scenes`: the object, a catalogue kind with a palette colour and a
pattern, on a textured ground slab) rendered from the cameras of a single view or of a
multi-view sheet (`views`: a VIEW_KINDS "reference" camera placed around the object, or a
"crop" of a dataset camera), with a caption naming some of the object's attributes
(`captions`). Views in which the object shows fewer than `min_object_pixels` pixels are
rejected and the whole sample is drawn again.

Per view (V views of H x W):
  rgb                  [V, H, W, 3] uint8   the scene with the object;
  background_rgb       [V, H, W, 3] uint8   the same view without it (the "original scene");
  depth                [V, H, W] float16    z-depth with the object (0 where rays miss);
  silhouette           [V, H, W] uint8      1 where the object is visible (occluders cut it);
  dilated_silhouettes  [V, K, H, W] uint8   the silhouette dilated by each of
                                            `dilation_radii` pixels (nested, growing);
  boxes                [V, 4] int16         silhouette bounding box [x0, y0, x1, y1), pixels;
  control_near_far     [V, 2] float32       the z-range for the control depth: the object's
                                            bounding sphere seen from the camera, padded, as
                                            `control_depth.selection_depth_range` gives the
                                            pipeline (control = normalize_control_depth(depth,
                                            near, far): near = 1, far = 0; the same rule makes
                                            the tiles of a sheet comparable);
  camera_to_world      [V, 3, 4] float32    OpenGL poses; intrinsics [V, 4] float32 fx fy cx cy;
  view_kinds           [V] uint8            index into VIEW_KINDS.
Per sample: caption, kind, color, pattern (strings), names_color / names_pattern (whether the
caption names them), object_sphere [4] (centre, radius), light [4] (direction to the light,
ambient share).

Everything is drawn from the one `np.random.Generator` passed in, so a sample is reproducible
from its seed (and the catalogue, i.e. which shared meshes exist).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from signerf_jax.default_model import appearance as appearance_lib
from signerf_jax.default_model import captions
from signerf_jax.default_model import scenes
from signerf_jax.default_model import views as views_lib
from signerf_jax.errors import InputError
from signerf_jax.geometry import reference_cameras

VIEW_KINDS = ("reference", "crop")  # How each view's camera is placed (`views`).


@dataclasses.dataclass(frozen=True)
class Sample:
  """A rendered sample (see the module docstring for the arrays).

  Attributes:
    attributes: the object's kind, colour and pattern.
    caption: its caption; names_color, names_pattern: which attributes the caption names.
    views: per-view arrays, each with a leading axis of V views.
    object_sphere: [4] the object's bounding sphere (centre, radius).
    light: [4] unit direction towards the light and the ambient share.
  """

  attributes: captions.Attributes
  caption: str
  names_color: bool
  names_pattern: bool
  views: dict[str, np.ndarray]
  object_sphere: np.ndarray
  light: np.ndarray

  def arrays(self) -> dict[str, np.ndarray]:
    """Everything as named arrays (what a shard stacks over samples)."""
    return {**self.views, "caption": np.array(self.caption), "kind": np.array(self.attributes.kind),
            "color": np.array(self.attributes.color),
            "pattern": np.array(self.attributes.pattern),
            "names_color": np.array(self.names_color), "names_pattern": np.array(self.names_pattern),
            "object_sphere": self.object_sphere.astype(np.float32),
            "light": self.light.astype(np.float32)}


def random_attributes(rng: np.random.Generator, catalogue) -> captions.Attributes:
  """A uniformly random kind (of the catalogue), colour and pattern."""
  return captions.Attributes(kind=catalogue[rng.integers(len(catalogue))].name,
                             color=appearance_lib.COLORS[rng.integers(len(appearance_lib.COLORS))],
                             pattern=appearance_lib.PATTERNS[rng.integers(len(appearance_lib.PATTERNS))])


def make_sample(rng: np.random.Generator, settings: scenes.SceneSampling,
                caption_settings: captions.CaptionSettings, sheet: bool,
                attributes: captions.Attributes | None = None) -> Sample:
  """A single view (sheet False) or a sheet of the same object; random attributes if None.

  Raises:
    InputError: no acceptable draw in `settings.max_attempts` (the settings make the object
      invisible or occluded too often).
  """
  catalogue = settings.catalogue()
  attributes = random_attributes(rng, catalogue) if attributes is None else attributes
  num_views = settings.sheet_tiles + 1 if sheet else 1
  for _ in range(settings.max_attempts):
    scene, background_scene = scenes.random_scene(rng, settings, attributes)
    chosen = views_lib.sample_cameras(rng, settings, scene, num_views, sheet)
    if chosen is None:
      continue
    cameras, view_kinds = chosen
    views = views_lib.render_views(scene, background_scene, cameras, settings)
    if views["silhouette"].sum((1, 2)).min() < settings.min_object_pixels:
      continue
    views["view_kinds"] = np.asarray(view_kinds, np.uint8)
    text, names_color, names_pattern = captions.random_caption(rng, attributes, caption_settings)
    center, radius = reference_cameras.selection_sphere(scenes.object_corners(scene))
    return Sample(attributes=attributes, caption=text, names_color=names_color,
                  names_pattern=names_pattern, views=views,
                  object_sphere=np.array([*center, radius]),
                  light=np.array([*scene.light_direction, scene.ambient]))
  raise InputError(f"no draw of a {attributes.kind} showed {settings.min_object_pixels} object "
                   f"pixels in every view in {settings.max_attempts} attempts",
                   field="default_model_scenes")
