"""Camera poses from images: COLMAP's features, matching and incremental mapping, through its
Python bindings (pycolmap), in-process.

Every step keeps its results in one COLMAP database, so an interrupted run resumes where it
stopped: images whose features are in the database are not extracted again and pairs already
matched are not matched again. Settings that change the features (camera model, image size,
feature count) start a new database (`Settings.feature_fingerprint`).

Choices for captures (measured on stitch's 110 frames, docs/results.md "Processing a capture"):
one camera shared by every image (a phone or a video keeps its lens); its principal point
refined with the rest from PRINCIPAL_POINT_MIN_IMAGES images on (a phone's crop or
stabilisation moves it off the centre: left at the centre, stitch's 110 recovered rotations
were off by 2.2 degrees, refined by 0.8; but it trades off against the rotations, and a few
dozen views do not pin it: 24 synthetic views were off by up to 1.1 degrees refined and 0.2
left at the true centre); and features from images at most 1024 px wide (SIFT at full phone
resolution costs minutes and registers no more views).
"""

from __future__ import annotations

import contextlib
import dataclasses
import tempfile
from pathlib import Path
from typing import Callable, Literal, Sequence

import numpy as np

from signerf_jax.data import image_pairs
from signerf_jax.data.colmap_bindings import pycolmap

CameraModel = Literal["OPENCV", "SIMPLE_RADIAL"]
Matching = Literal["auto", "exhaustive", "sequential"]
# Images per feature-extraction call: the progress bar moves once per call.
EXTRACTION_BATCH = 8
# Pairs per matching call, likewise.
MATCHING_BATCH = 256
# The fewest images whose shared camera gets its principal point refined (see above).
PRINCIPAL_POINT_MIN_IMAGES = 50
# COLMAP's own default seed is random per run; a fixed one makes reruns repeatable.
RANDOM_SEED = 0


@dataclasses.dataclass(frozen=True)
class Settings:
  """How a capture's cameras are recovered.

  Attributes:
    camera_model: "OPENCV" (k1, k2, p1, p2: phones, most lenses) or "SIMPLE_RADIAL" (one k1,
      fewer unknowns for few images).
    shared_camera: one camera (intrinsics and distortion) for every image; False gives each
      image its own (photos from several devices or zoom settings).
    max_image_size: features are found in images scaled down to at most this many pixels on
      their longer side.
    max_features: SIFT features kept per image.
    matching: "exhaustive" (every pair), "sequential" (neighbours in capture order plus
      retrieved look-alikes, which close loops), or "auto": exhaustive up to
      `exhaustive_limit` images, sequential above.
    exhaustive_limit: the largest capture "auto" matches exhaustively.
    sequential_overlap: neighbours in capture order each image is matched with.
    retrieval_neighbours: look-alike images each image is matched with (sequential matching).
    refine_principal_point: refine the shared camera's principal point in bundle adjustment
      ("auto": from PRINCIPAL_POINT_MIN_IMAGES images on).
  """

  camera_model: CameraModel = "OPENCV"
  shared_camera: bool = True
  max_image_size: int = 1024
  max_features: int = 4096
  matching: Matching = "auto"
  exhaustive_limit: int = 100
  sequential_overlap: int = 10
  retrieval_neighbours: int = 10
  refine_principal_point: Literal["auto", "yes", "no"] = "auto"

  def feature_fingerprint(self) -> dict[str, object]:
    """The settings the database's features depend on."""
    return {"camera_model": self.camera_model, "shared_camera": self.shared_camera,
            "max_image_size": self.max_image_size, "max_features": self.max_features}

  def matching_for(self, num_images: int) -> str:
    """The matching used for `num_images` images ("exhaustive" or "sequential")."""
    if self.matching != "auto":
      return self.matching
    return "exhaustive" if num_images <= self.exhaustive_limit else "sequential"

  def refines_principal_point(self, num_images: int) -> bool:
    """Whether bundle adjustment refines the principal point of a capture of `num_images`."""
    if not self.shared_camera or self.refine_principal_point == "no":
      return False
    return self.refine_principal_point == "yes" or num_images >= PRINCIPAL_POINT_MIN_IMAGES


Progress = Callable[[int], None]


@contextlib.contextmanager
def _database(path: Path):
  """The COLMAP database at `path`, closed afterwards (the pycolmap steps open it themselves)."""
  database = pycolmap.Database.open(str(path))
  try:
    yield database
  finally:
    database.close()


def _image_ids(database_path: Path) -> dict[str, int]:
  """Image name -> database id of the images whose features are in the database."""
  if not database_path.exists():
    return {}
  with _database(database_path) as database:
    return {image.name: image.image_id for image in database.read_all_images()
            if database.exists_keypoints(image.image_id)}


def extract_features(database_path: Path, image_directory: Path, names: Sequence[str],
                     settings: Settings, advance: Progress) -> int:
  """SIFT features of the images `names` (relative to `image_directory`) not yet in the
  database; `advance(k)` after each batch of k images. Returns how many were extracted."""
  done = _image_ids(database_path)
  todo = [name for name in names if name not in done]
  advance(len(names) - len(todo))
  extraction = pycolmap.FeatureExtractionOptions(max_image_size=settings.max_image_size)
  extraction.sift.max_num_features = settings.max_features
  reader = pycolmap.ImageReaderOptions(camera_model=settings.camera_model)
  mode = pycolmap.CameraMode.SINGLE if settings.shared_camera else pycolmap.CameraMode.PER_IMAGE
  for start in range(0, len(todo), EXTRACTION_BATCH):
    batch = todo[start:start + EXTRACTION_BATCH]
    if settings.shared_camera and done:
      # Later batches join the first batch's camera (each call would otherwise make one).
      with _database(database_path) as database:
        reader.existing_camera_id = database.read_all_images()[0].camera_id
    pycolmap.extract_features(database_path, image_directory, image_names=batch,
                              camera_mode=mode, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    done.update(_image_ids(database_path))
    advance(len(batch))
  return len(todo)


def pairs_to_match(database_path: Path, names: Sequence[str], settings: Settings
                   ) -> list[tuple[str, str]]:
  """The image pairs to match (see `image_pairs`), by name; `names` in capture order."""
  if settings.matching_for(len(names)) == "exhaustive":
    indices = image_pairs.exhaustive_pairs(len(names))
  else:
    ids = _image_ids(database_path)
    with _database(database_path) as database:
      descriptors = [database.read_descriptors(ids[name]).data for name in names]
    indices = sorted(set(image_pairs.sequential_pairs(len(names), settings.sequential_overlap))
                     | set(image_pairs.retrieval_pairs(descriptors,
                                                       settings.retrieval_neighbours)))
  return [(names[i], names[j]) for i, j in indices]


def match(database_path: Path, pairs: Sequence[tuple[str, str]], advance: Progress) -> int:
  """Matches and geometrically verifies the `pairs` not yet matched; `advance(k)` after each
  batch of k pairs. Returns how many pairs were matched."""
  ids = _image_ids(database_path)
  with _database(database_path) as database:
    todo = [pair for pair in pairs
            if not database.exists_two_view_geometry(ids[pair[0]], ids[pair[1]])]
  advance(len(pairs) - len(todo))
  with tempfile.TemporaryDirectory(prefix="signerf-pairs-") as scratch:
    pair_list = Path(scratch) / "pairs.txt"
    for start in range(0, len(todo), MATCHING_BATCH):
      batch = todo[start:start + MATCHING_BATCH]
      pair_list.write_text("".join(f"{first} {second}\n" for first, second in batch))
      pycolmap.match_image_pairs(
          database_path, pairing_options=pycolmap.ImportedPairingOptions(
              match_list_path=str(pair_list)), device=pycolmap.Device.cpu)
      advance(len(batch))
  return len(todo)


def reconstruct(database_path: Path, image_directory: Path, num_images: int, settings: Settings,
                advance: Progress) -> list[pycolmap.Reconstruction]:
  """Incremental mapping with bundle adjustment of the `num_images` images in the database;
  `advance(1)` per registered image. Returns the models found (COLMAP starts a new one where
  registration breaks off), largest first."""
  options = pycolmap.IncrementalPipelineOptions()
  options.ba_refine_principal_point = settings.refines_principal_point(num_images)
  options.random_seed = RANDOM_SEED
  # Mapping writes snapshots and its models to disk: a scratch folder outside the dataset.
  with tempfile.TemporaryDirectory(prefix="signerf-mapping-") as scratch:
    models = pycolmap.incremental_mapping(
        database_path, image_directory, scratch, options=options,
        initial_image_pair_callback=lambda: advance(2), next_image_callback=lambda: advance(1))
  return sorted(models.values(), key=lambda model: model.num_reg_images(), reverse=True)


def world_from_camera_opengl(image: pycolmap.Image) -> np.ndarray:
  """[4, 4] camera-to-world of a registered image in OpenGL's camera axes (x right, y up,
  looking down -z: nerfstudio's convention), from COLMAP's world-to-camera (y down, +z ahead)."""
  matrix = np.eye(4)
  matrix[:3] = image.cam_from_world().inverse().matrix()
  return matrix @ np.diag([1.0, -1.0, -1.0, 1.0])


def quiet_logging() -> None:
  """COLMAP logs every step's details to stderr; the command reports progress itself."""
  pycolmap.logging.minloglevel = int(pycolmap.logging.Level.ERROR)
