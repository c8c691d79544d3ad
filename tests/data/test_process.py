"""`signerf process`: a synthetic capture with known poses, as photos and as a video, goes through
COLMAP and comes back as a dataset with the true poses (up to a similarity); reruns resume;
bad captures are clear errors."""

from __future__ import annotations

import json
import shutil
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from signerf_jax import cli, files, ownership
from signerf_jax.data import (capture_import, image_pairs, load_dataset, pose_alignment,
                              synthetic, synthetic_render)

# Textured enough for SIFT (the speckled ground) and views close enough to match: every one of
# the 24 registers (the default checker ground and wider elevations register fewer).
SCENE = synthetic.SceneSettings(ground_texture="speckle", ground_texture_frequency=25.0)
RIG = synthetic_render.CameraRig(num_views=24, image_size=256,
                                 elevation_range_degrees=(25.0, 55.0))


def render_scene(directory: Path, rig: synthetic_render.CameraRig) -> Path:
  with ownership.claimed(directory, ownership.DATASET):
    synthetic_render.generate(directory, seed=0, settings=SCENE, rig=rig)
  return directory


def run(argv, capsys) -> tuple[int, dict, str]:
  capsys.readouterr()
  code = cli.main(["process", *argv])
  out, err = capsys.readouterr()
  return code, (json.loads(out.strip().splitlines()[-1]) if code == 0 else {}), err


def true_and_recovered_poses(scene: Path, processed: Path):
  truth = {Path(frame["file_path"]).name: np.asarray(frame["transform_matrix"])
           for frame in files.read_json(scene / "transforms.json")["frames"]}
  recovered = {Path(frame["file_path"]).name: np.asarray(frame["transform_matrix"])
               for frame in files.read_json(processed / "transforms.json")["frames"]}
  names = sorted(recovered)
  return np.stack([recovered[name] for name in names]), np.stack([truth[name] for name in names])


@pytest.fixture(scope="module")
def processed_photos(tmp_path_factory):
  root = tmp_path_factory.mktemp("process")
  scene = render_scene(root / "scene", RIG)
  code = cli.main(["process", "--images", str(scene / "images"), "--out", str(root / "data")])
  assert code == 0
  return scene, root / "data"


@pytest.mark.slow  # COLMAP on 24 views
def test_every_synthetic_view_registers_at_its_true_pose(processed_photos):
  scene, data = processed_photos
  summary = files.read_json(data / "process.json")
  assert summary["registered"] == RIG.num_views and summary["unregistered"] == []
  assert summary["matching"] == "exhaustive" and summary["other_models"] == []
  recovered, truth = true_and_recovered_poses(scene, data)
  rotation, position, radius = pose_alignment.pose_errors(recovered, truth)
  assert np.max(rotation) < 1.0  # degrees
  assert np.max(position) < 0.01 * radius


@pytest.mark.slow  # COLMAP on 24 views
def test_the_processed_capture_loads_as_a_dataset_with_its_downscaled_copies(processed_photos):
  _, data = processed_photos
  for factor in capture_import.DOWNSCALE_FACTORS:
    copy = files.read_image(data / f"images_{factor}" / "frame_00000.png")
    assert copy.shape[:2] == (256 // factor, 256 // factor)
  dataset = load_dataset(data, split="all", downscale=4)
  assert dataset.num_images == RIG.num_views and dataset.images.shape[1:3] == (64, 64)
  assert np.all(np.isfinite(np.asarray(dataset.cameras.camera_to_world)))


@pytest.mark.slow  # COLMAP on 24 views
def test_a_rerun_reuses_the_features_and_matches(processed_photos, tmp_path, monkeypatch, capsys):
  scene, data = processed_photos
  copy = shutil.copytree(data, tmp_path / "data", symlinks=True)
  import pycolmap

  def not_again(*args, **kwargs):
    raise AssertionError("recomputed what the database holds")

  monkeypatch.setattr(pycolmap, "extract_features", not_again)
  monkeypatch.setattr(pycolmap, "match_image_pairs", not_again)
  code, summary, _ = run(["--images", str(scene / "images"), "--out", str(copy)], capsys)
  assert code == 0
  assert summary["features_extracted"] == 0 and summary["pairs_matched"] == 0
  assert summary["registered"] == RIG.num_views


@pytest.mark.slow  # COLMAP on 24 views
def test_changed_feature_settings_start_a_new_database(processed_photos, tmp_path, capsys):
  scene, data = processed_photos
  copy = shutil.copytree(data, tmp_path / "data", symlinks=True)
  code, summary, _ = run(["--images", str(scene / "images"), "--out", str(copy),
                          "--max_features", "2000"], capsys)
  assert code == 0 and summary["features_extracted"] == RIG.num_views


def write_video(path: Path, frames: list[np.ndarray]) -> None:
  height, width = frames[0].shape[:2]
  writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (width, height))
  for frame in frames:
    writer.write(frame)
  writer.release()


@pytest.mark.slow  # COLMAP on 24 views
def test_a_video_keeps_its_sharpest_frames_and_registers_them(processed_photos, tmp_path, capsys):
  # A walk around the scene (the views ordered by azimuth), each frame between two blurred
  # copies (motion blur): the sharp ones are what the selection must keep, and sequential
  # matching, with retrieval closing the loop, must tie them together.
  scene, _ = processed_photos
  truth = files.read_json(scene / "transforms.json")["frames"]
  azimuth = [np.arctan2(frame["transform_matrix"][1][3], frame["transform_matrix"][0][3])
             for frame in truth]
  frames = []
  for index in np.argsort(azimuth):
    image = cv2.imread(str(scene / truth[index]["file_path"]))
    frames += [cv2.GaussianBlur(image, (0, 0), 3.0), image, cv2.GaussianBlur(image, (0, 0), 2.0)]
  write_video(tmp_path / "walk.avi", frames)
  code, summary, _ = run(["--video", str(tmp_path / "walk.avi"), "--out", str(tmp_path / "data"),
                          "--max_frames", str(RIG.num_views), "--matching", "sequential"], capsys)
  assert code == 0
  names = sorted(path.name for path in (tmp_path / "data" / "images").iterdir())
  assert names == [f"frame_{3 * index + 1:05d}.jpg" for index in range(RIG.num_views)]
  assert summary["registered"] == RIG.num_views and summary["matching"] == "sequential"
  assert summary["pairs"] < RIG.num_views * (RIG.num_views - 1) // 2


def exif_rotated_jpeg(image: np.ndarray, orientation: int) -> bytes:
  """A JPEG of `image` (BGR) whose EXIF tag says to turn it (6: 90 degrees clockwise)."""
  jpeg = cv2.imencode(".jpg", image)[1].tobytes()
  entry = struct.pack("<HHIHH", 0x0112, 3, 1, orientation, 0)
  tiff = b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", 1) + entry + struct.pack("<I", 0)
  body = b"Exif\x00\x00" + tiff
  return jpeg[:2] + b"\xff\xe1" + struct.pack(">H", len(body) + 2) + body + jpeg[2:]


def test_photos_are_turned_upright_by_their_exif_orientation(tmp_path):
  image = np.zeros((40, 80, 3), np.uint8)
  image[:, :20] = 255  # white on the left
  (tmp_path / "portrait.jpg").write_bytes(exif_rotated_jpeg(image, 6))
  upright = capture_import.read_upright(tmp_path / "portrait.jpg")
  assert upright.shape == (80, 40, 3)
  assert upright[:20].mean() > 0.9 and upright[40:].mean() < 0.1  # the left is now the top


def test_frames_spread_over_the_clip_and_pick_the_sharpest_of_each_stretch():
  sharpness = np.array([1, 5, 2, 9, 1, 1, 3, 2, 8, 1], float)
  assert capture_import.choose_frames(sharpness, 3).tolist() == [1, 3, 8]
  assert capture_import.choose_frames(sharpness, 20).tolist() == list(range(10))


def test_sequential_pairs_reach_neighbours_and_quadratic_offsets():
  pairs = set(image_pairs.sequential_pairs(40, overlap=3))
  assert {(0, 1), (0, 2), (0, 3), (0, 4), (0, 8), (0, 16), (0, 32)} <= pairs
  assert (0, 5) not in pairs and (39, 40) not in pairs
  assert len(image_pairs.exhaustive_pairs(6)) == 15


def test_retrieval_pairs_find_the_views_that_share_features():
  random = np.random.default_rng(0)
  # Four places, three views of each, shuffled: views of one place share most descriptors.
  places = [random.integers(0, 256, (300, 128)) for _ in range(4)]
  order = random.permutation(12)
  descriptors = [np.concatenate([places[view // 3][random.permutation(300)[:200]],
                                 random.integers(0, 256, (50, 128))]) for view in order]
  pairs = image_pairs.retrieval_pairs(descriptors, neighbours=2)
  place = order // 3
  assert all(place[i] == place[j] for i, j in pairs)
  assert len(pairs) == 12  # each place's three views, all pairs


@pytest.mark.parametrize("perturbed", [False, True])
def test_pose_errors_vanish_after_the_unknown_similarity_and_nothing_else(perturbed):
  random = np.random.default_rng(1)

  def rotation_matrix():
    matrix = np.linalg.qr(random.normal(size=(3, 3)))[0]
    return matrix * np.sign(np.linalg.det(matrix))

  truth = np.tile(np.eye(4), (6, 1, 1))
  truth[:, :3, 3] = random.normal(size=(6, 3)) * 3
  truth[:, :3, :3] = [rotation_matrix() for _ in range(6)]
  rotation = rotation_matrix()
  estimated = truth.copy()
  estimated[:, :3, :3] = rotation @ truth[:, :3, :3]
  estimated[:, :3, 3] = 0.01 * truth[:, :3, 3] @ rotation.T + [5.0, -2.0, 1e3]
  if perturbed:  # one camera off by 0.1 in the truth's units: it must show, not be absorbed
    estimated[0, :3, 3] += 0.01 * rotation @ [0.1, 0.0, 0.0]
  degrees, position, radius = pose_alignment.pose_errors(estimated, truth)
  assert radius > 1
  if perturbed:
    assert 0.05 < position[0] < 0.1
  else:
    assert np.max(degrees) < 1e-4 and np.max(position) < 1e-6 * radius


def test_a_folder_without_images_is_a_clear_error(tmp_path, capsys):
  (tmp_path / "photos").mkdir()
  (tmp_path / "photos" / "notes.txt").write_text("no photos here")
  code, _, err = run(["--images", str(tmp_path / "photos"), "--out", str(tmp_path / "d")], capsys)
  assert code == 2 and "holds no images" in err and "photos" in err.splitlines()[-1]


def test_an_unreadable_photo_is_named(tmp_path, capsys):
  photos = tmp_path / "photos"
  photos.mkdir()
  files.write_image(photos / "good.png", np.ones((8, 8, 3)) * 0.5)
  (photos / "broken.jpg").write_bytes(b"\xff\xd8 not really a jpeg")
  code, _, err = run(["--images", str(photos), "--out", str(tmp_path / "d")], capsys)
  assert code == 2 and "broken.jpg" in err.splitlines()[-1] and "not a readable image" in err


def test_an_unreadable_video_is_named(tmp_path, capsys):
  (tmp_path / "clip.mp4").write_bytes(b"\x00" * 1000)
  code, _, err = run(["--video", str(tmp_path / "clip.mp4"), "--out", str(tmp_path / "d")],
                     capsys)
  assert code == 2 and "clip.mp4" in err.splitlines()[-1] and "not a readable video" in err


def test_photos_that_do_not_overlap_are_refused_with_advice(tmp_path, capsys):
  photos = tmp_path / "photos"
  random = np.random.default_rng(0)
  for index in range(6):  # unrelated noise: nothing matches
    files.write_image(photos / f"noise_{index}.png", random.uniform(size=(96, 96, 3)))
  code, _, err = run(["--images", str(photos), "--out", str(tmp_path / "d")], capsys)
  message = err.strip().splitlines()[-1]
  assert code == 2 and "of 6 images registered" in message and "overlap" in message
  assert not (tmp_path / "d" / "transforms.json").exists()
  assert files.read_json(tmp_path / "d" / "process.json")["images"] == 6
