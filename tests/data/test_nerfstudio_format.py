import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from signerf_jax import files, ownership
from signerf_jax.data import load_dataset, load_views, nerfstudio, poses, views, write_nerfstudio
from signerf_jax.errors import InputError


def assert_same_cameras(actual, expected):
  assert (actual.width, actual.height) == (expected.width, expected.height)
  for name in ("camera_to_world", "fx", "fy", "cx", "cy", "distortion"):
    np.testing.assert_array_equal(getattr(actual, name), getattr(expected, name), err_msg=name)


# (distortion, fisheye, the camera model the writer picks for it)
LENSES = {
    "pinhole": (None, False, "PINHOLE"),
    "opencv": ((-0.12, 0.03, 0.001, -0.002), False, "OPENCV"),
    "opencv with k3": ((-0.12, 0.03, 0.001, -0.002, 0.004), False, "OPENCV"),
    "rational": ((-0.12, 0.03, 0.001, -0.002, 0.004, 0.2, -0.01, 0.003), False, "FULL_OPENCV"),
    "fisheye": ((0.05, -0.01, 0.002, -0.0005), True, "OPENCV_FISHEYE"),
    "equidistant fisheye": (None, True, "OPENCV_FISHEYE"),
}


@pytest.mark.parametrize("lens", LENSES)
@pytest.mark.parametrize("per_frame_intrinsics", [False, True])
def test_write_then_read_gives_identical_cameras_and_data(tmp_path, dataset_factory, lens,
                                                          per_frame_intrinsics):
  distortion, fisheye, camera_model = LENSES[lens]
  similarity = poses.similarity(0.5, poses.rotation_between([0, 0, 1], [0, 1, 0]), [0.1, 0, 0])
  dataset = dataset_factory(distortion=distortion, fisheye=fisheye,
                            per_frame_intrinsics=per_frame_intrinsics,
                            world_from_source=similarity)
  path = write_nerfstudio(tmp_path, dataset, provenance={"made_by": "test"})
  meta = files.read_json(path)
  assert ("fl_x" in meta) != per_frame_intrinsics
  assert meta["camera_model"] == camera_model
  assert set(nerfstudio.DISTORTION_SLOTS[camera_model]) <= set(meta)
  assert meta["signerf"]["provenance"] == {"made_by": "test"}

  restored = load_dataset(tmp_path, split="all")
  assert restored.cameras.fisheye == fisheye
  assert_same_cameras(restored.cameras, dataset.cameras)
  np.testing.assert_allclose(restored.images, dataset.images, atol=0.5 / 255 + 1e-6)
  np.testing.assert_allclose(restored.masks, dataset.masks, atol=0.5 / 255)
  np.testing.assert_array_equal(restored.depths, dataset.depths)
  np.testing.assert_array_equal(restored.extras["object_masks"], dataset.extras["object_masks"])
  np.testing.assert_allclose(restored.world_from_source, dataset.world_from_source, atol=1e-7)
  np.testing.assert_array_equal(restored.scene_bounds, dataset.scene_bounds)
  np.testing.assert_array_equal(restored.background_color, dataset.background_color)
  assert (restored.scene_kind, restored.near, restored.far) == ("bounded", 1.5, 3.5)


def test_split_holds_out_every_nth_frame_and_shares_the_frame(tmp_path, dataset_factory):
  dataset = dataset_factory(count=10)
  write_nerfstudio(tmp_path, dataset)
  train = load_dataset(tmp_path, split="train", eval_every=4)
  held_out = load_dataset(tmp_path, split="eval", eval_every=4)
  assert held_out.image_names == tuple(f"images/frame_{i:05d}.png" for i in (0, 4, 8))
  assert train.num_images == 7 and "images/frame_00004.png" not in train.image_names
  np.testing.assert_array_equal(held_out.cameras.camera_to_world,
                                dataset.cameras.camera_to_world[[0, 4, 8]])
  np.testing.assert_array_equal(train.world_from_source, held_out.world_from_source)


@pytest.mark.parametrize("split", ["train", "eval"])
def test_the_views_without_pixels_are_the_dataset_s_and_read_no_image(tmp_path, dataset_factory,
                                                                       split):
  write_nerfstudio(tmp_path, dataset_factory(count=10))
  dataset = load_dataset(tmp_path, split=split, eval_every=4, downscale=2)
  for image in (tmp_path / "images").iterdir():
    image.unlink()  # What the views are read from must not include a pixel.
  views = load_views(tmp_path, split=split, eval_every=4, downscale=2)
  assert views.image_names == dataset.image_names and views.num_images == dataset.num_images
  assert views.scene_kind == dataset.scene_kind
  assert_same_cameras(views.cameras, dataset.cameras)
  for name in ("scene_bounds", "world_from_source"):
    np.testing.assert_array_equal(getattr(views, name), getattr(dataset, name), err_msg=name)
  assert_same_cameras(dataset.views.cameras, dataset.cameras)


def test_downscale_prefers_prepared_folders_and_otherwise_averages(tmp_path, dataset_factory):
  dataset = dataset_factory(width=12, height=8)
  write_nerfstudio(tmp_path, dataset)
  resampled = load_dataset(tmp_path, split="all", downscale=2)
  assert (resampled.width, resampled.height) == (6, 4)
  assert_same_cameras(resampled.cameras, dataset.cameras.downscaled(2))
  quantised = np.round(dataset.images[0] * 255) / 255
  np.testing.assert_allclose(resampled.images[0],
                             quantised.reshape(4, 2, 6, 2, 3).mean((1, 3)), atol=1e-5)
  # Depth and object ids are sampled, never averaged (at the pixel under each centre).
  np.testing.assert_array_equal(resampled.depths[0], dataset.depths[0][1::2, 1::2])
  np.testing.assert_array_equal(resampled.extras["object_masks"],
                                dataset.extras["object_masks"][:, 1::2, 1::2])

  marker = np.full((4, 6, 3), 0.2, np.float32)
  for index in range(dataset.num_images):
    files.write_image(tmp_path / "images_2" / f"frame_{index:05d}.png", marker)
  prepared = load_dataset(tmp_path, split="all", downscale=2)
  np.testing.assert_allclose(prepared.images, 0.2, atol=1 / 255)


def test_depth_png_uses_the_unit_scale_and_depth_follows_normalisation(tmp_path,
                                                                       dataset_factory):
  dataset = dataset_factory(count=3, with_extras=False)
  write_nerfstudio(tmp_path, dataset)
  meta = files.read_json(tmp_path / "transforms.json")
  depth_millimetres = np.full((dataset.height, dataset.width), 2500.0)
  for frame in meta["frames"]:
    frame["depth_file_path"] = frame["file_path"].replace("images/", "depth/")
    files.write_image(tmp_path / frame["depth_file_path"], depth_millimetres / 65535, 16)
  # Bounds outside the unit box: the reader scales the scene (here by 1/2), depths with it.
  meta["signerf"]["scene_bounds"] = [[-2, -2, -2], [2, 2, 2]]
  del meta["signerf"]["near"], meta["signerf"]["far"]
  files.write_json(tmp_path / "transforms.json", meta)
  restored = load_dataset(tmp_path, split="all")
  np.testing.assert_allclose(restored.depths, 1.25, rtol=1e-6)
  np.testing.assert_allclose(restored.cameras.positions, dataset.cameras.positions / 2,
                             atol=1e-6)
  np.testing.assert_array_equal(restored.scene_bounds, [[-1, -1, -1], [1, 1, 1]])


def test_rgba_images_are_composited_on_the_background(tmp_path, dataset_factory):
  dataset = dataset_factory(count=2, with_extras=False)
  write_nerfstudio(tmp_path, dataset)
  rgba = np.zeros((dataset.height, dataset.width, 4), np.float32)
  rgba[..., 0], rgba[..., 3] = 1.0, 0.25
  files.write_image(tmp_path / "images/frame_00000.png", rgba)
  restored = load_dataset(tmp_path, split="all")
  # 25% red over the dataset's background (1, 0.5, 0).
  np.testing.assert_allclose(restored.images[0], np.broadcast_to([1.0, 0.375, 0.0], (9, 12, 3)),
                             atol=2 / 255)


def test_plain_capture_is_centred_on_what_its_cameras_look_at(tmp_path, dataset_factory):
  dataset = dataset_factory(count=8, with_extras=False)
  source_from_scene = poses.similarity(7.0, poses.rotation_between([0, 0, 1], [1, 0, 0]),
                                       [3.0, -2.0, 5.0])
  write_nerfstudio(tmp_path, dataclasses.replace(
      dataset, cameras=poses.transform_cameras(source_from_scene, dataset.cameras)))
  meta = files.read_json(tmp_path / "transforms.json")
  del meta["signerf"], meta["applied_transform"]
  files.write_json(tmp_path / "transforms.json", meta)
  restored = load_dataset(tmp_path, split="all")
  assert restored.scene_kind == "unbounded" and restored.background_color is None
  positions = np.asarray(restored.cameras.positions)
  # The cameras lie inside the inner region, the farthest on its border.
  assert np.max(np.abs(positions)) == pytest.approx(1.0, abs=1e-5)
  # The ring's cameras look at the origin of their frame, which the source frame moved to
  # (3, -2, 5): that point, not the cameras' centroid, becomes the scene's centre.
  np.testing.assert_allclose(poses.transform_points(restored.world_from_source, [3.0, -2.0, 5.0]),
                             0.0, atol=1e-5)
  assert restored.frame["center_in_source_units"] == pytest.approx([3.0, -2.0, 5.0], abs=1e-5)
  # The ring's cameras share one up vector: it is turned onto +z.
  np.testing.assert_allclose(np.asarray(restored.cameras.camera_to_world)[:, :, 1].mean(0)
                             @ [0, 0, 1], np.linalg.norm(
                                 np.asarray(dataset.cameras.camera_to_world)[:, :, 1].mean(0)),
                             atol=1e-5)
  # world_from_source maps the file's frame into the scene: cameras agree through it.
  np.testing.assert_allclose(
      poses.transform_points(restored.world_from_source,
                             np.asarray(dataset.cameras.positions) @ source_from_scene[:3, :3].T
                             + source_from_scene[:3, 3]), positions, atol=1e-5)


def test_forward_facing_capture_is_detected(tmp_path, dataset_factory):
  dataset = dataset_factory(count=4, with_extras=False)
  camera_to_world = np.asarray(dataset.cameras.camera_to_world).copy()
  camera_to_world[:, :, :3] = np.eye(3)
  camera_to_world[:, :, 3] = np.stack([np.linspace(-1, 1, 4), np.zeros(4), np.zeros(4)], -1)
  write_nerfstudio(tmp_path, dataclasses.replace(
      dataset, cameras=dataset.cameras.replace(camera_to_world=camera_to_world)))
  meta = files.read_json(tmp_path / "transforms.json")
  del meta["signerf"]
  files.write_json(tmp_path / "transforms.json", meta)
  assert load_dataset(tmp_path).scene_kind == "forward_facing"
  assert load_dataset(tmp_path, scene_kind="unbounded").scene_kind == "unbounded"
  bounded = load_dataset(tmp_path, scene_kind="bounded", background_color=(0, 0, 0))
  np.testing.assert_array_equal(bounded.background_color, [0, 0, 0])


def test_rewriting_a_directory_removes_stale_frames_and_never_mixes(tmp_path, dataset_factory,
                                                                    monkeypatch):
  directory = tmp_path / "dataset"
  with ownership.claimed(directory, ownership.DATASET):  # As `signerf synthesize` writes.
    write_nerfstudio(directory, dataset_factory(count=6))
  smaller = dataset_factory(count=3, seed=1)
  # Interrupt the second write half-way: no transforms.json may point at a mix of files.
  calls = []

  def failing_write_exr(path, array):
    calls.append(path)
    if len(calls) == 2:
      raise KeyboardInterrupt
    files.write_exr(path, array)

  monkeypatch.setattr(nerfstudio.files, "write_exr", failing_write_exr)
  with pytest.raises(KeyboardInterrupt):
    with ownership.claimed(directory, ownership.DATASET):
      write_nerfstudio(directory, smaller)
  assert not (directory / "transforms.json").exists()
  with pytest.raises(InputError, match="transforms.json"):
    load_dataset(directory)
  monkeypatch.undo()

  with ownership.claimed(directory, ownership.DATASET):
    write_nerfstudio(directory, smaller)
  assert sorted(p.name for p in (directory / "images").iterdir()) == [
      f"frame_{i:05d}.png" for i in range(3)]
  # No temporary files left behind (the marker folder is the record of what was written).
  assert [path.name for path in directory.rglob(".*")] == [ownership.MARKER_FOLDER]
  restored = load_dataset(directory, split="all")
  np.testing.assert_array_equal(restored.depths, smaller.depths)


def test_frames_without_optional_files_get_neutral_values(tmp_path, dataset_factory):
  dataset = dataset_factory(count=3)
  write_nerfstudio(tmp_path, dataset)
  meta = json.loads((tmp_path / "transforms.json").read_text())
  for key in ("mask_path", "depth_file_path", "object_mask_path"):
    del meta["frames"][1][key]
  files.write_json(tmp_path / "transforms.json", meta)
  restored = load_dataset(tmp_path, split="all")
  assert np.all(restored.masks[1] == 1) and np.all(restored.depths[1] == 0)
  assert np.all(restored.extras["object_masks"][1] == 0)


# Issue 68: every path a transforms.json names stays inside the dataset folder, and values that
# used to end in a traceback or a silently wrong scene are errors naming the file and entry.


def written_scene(tmp_path, dataset_factory, count=5, **options):
  """A nerfstudio scene in tmp_path/scene; (its folder, its transforms.json, the json read)."""
  root = tmp_path / "scene"
  write_nerfstudio(root, dataset_factory(count=count, **options))
  path = root / "transforms.json"
  return root, path, files.read_json(path)


def test_contained_path_keeps_paths_inside_the_folder_after_symlinks(tmp_path):
  root = tmp_path / "data"
  (root / "images").mkdir(parents=True)
  (root / "images" / "a.png").write_bytes(b"")
  (tmp_path / "secret.png").write_bytes(b"")
  assert files.contained_path(root, "images/a.png", "t.json", "f") == root / "images/a.png"
  assert files.contained_path(root, "./images/../images/a.png", "t.json", "f").resolve() == (
      root / "images/a.png").resolve()
  assert files.contained_path(root, root / "images/a.png", "t.json", "f") == root / "images/a.png"
  # A dataset folder reached through a symlink is fine: both sides are resolved.
  (tmp_path / "link").symlink_to(root)
  assert files.contained_path(tmp_path / "link", "images/a.png", "t.json", "f").is_file()
  (root / "images" / "out.png").symlink_to(tmp_path / "secret.png")
  for outside in ("../secret.png", str(tmp_path / "secret.png"), "images/out.png",
                  "images/../../secret.png"):
    with pytest.raises(InputError, match="points outside the folder") as error:
      files.contained_path(root, outside, "t.json", "frames[3].file_path")
    assert (error.value.path, error.value.field) == ("t.json", "frames[3].file_path")
  for bad in ("", 3, None):
    with pytest.raises(InputError) as error:
      files.contained_path(root, bad, "t.json", "frames[0].file_path")
    assert error.value.field == "frames[0].file_path"


@pytest.mark.parametrize("key", ["file_path", "mask_path", "depth_file_path",
                                 "object_mask_path"])
def test_a_frame_file_outside_the_dataset_folder_is_refused(tmp_path, dataset_factory, key):
  root, path, meta = written_scene(tmp_path, dataset_factory)
  # The file exists, so only the containment check stands between it and the reader.
  secret = tmp_path / "secret.png"
  files.write_image(secret, np.ones((9, 12, 3)))
  meta["frames"][3][key] = "../secret.png"
  files.write_json(path, meta)
  with pytest.raises(InputError, match="points outside the folder") as error:
    load_dataset(root, split="all")
  assert (error.value.path, error.value.field) == (str(path), f"frames[3].{key}")


def test_an_extensionless_file_path_found_through_a_symlink_out_is_refused(tmp_path,
                                                                           dataset_factory):
  root, path, meta = written_scene(tmp_path, dataset_factory)
  image = root / meta["frames"][2]["file_path"]
  image.rename(tmp_path / "elsewhere.png")
  image.symlink_to(tmp_path / "elsewhere.png")
  meta["frames"][2]["file_path"] = meta["frames"][2]["file_path"].removesuffix(".png")
  files.write_json(path, meta)
  with pytest.raises(InputError, match="points outside") as error:
    load_dataset(root, split="all")
  assert error.value.field == "frames[2].file_path"


@pytest.mark.parametrize("absolute", [False, True])
def test_extensionless_file_paths_load_from_a_relative_dataset_folder(tmp_path, dataset_factory,
                                                                     monkeypatch, absolute):
  # As ../shared/data/stitch, whose file paths have no extension, given as a relative path.
  root, path, meta = written_scene(tmp_path, dataset_factory)
  for frame in meta["frames"]:
    frame["file_path"] = frame["file_path"].removesuffix(".png")
    if absolute:
      frame["file_path"] = str(root.resolve() / frame["file_path"])
  files.write_json(path, meta)
  # Two folders deep: joining such a relative folder to itself leads elsewhere.
  (tmp_path / "deep").mkdir()
  root = root.rename(tmp_path / "deep" / "scene")
  if absolute:
    for frame in meta["frames"]:
      frame["file_path"] = frame["file_path"].replace(str(path.parent.resolve()), str(root))
    files.write_json(root / path.name, meta)
  (tmp_path / "elsewhere").mkdir()
  monkeypatch.chdir(tmp_path / "elsewhere")
  relative = Path("..") / "deep" / "scene"
  assert load_dataset(relative, split="all").num_images == len(meta["frames"])


def test_a_split_file_naming_a_file_outside_is_refused_naming_that_file(tmp_path,
                                                                        dataset_factory):
  root, path, meta = written_scene(tmp_path, dataset_factory)
  path.rename(root / "transforms_train.json")
  test_meta = dict(meta, frames=[dict(meta["frames"][0], file_path="/etc/hostname")])
  files.write_json(root / "transforms_test.json", test_meta)
  with pytest.raises(InputError, match="points outside") as error:
    load_dataset(root, split="all")
  assert error.value.path == str(root / "transforms_test.json")
  assert error.value.field == "frames[0].file_path"


def test_a_frame_listed_twice_names_both_entries(tmp_path, dataset_factory):
  root, path, meta = written_scene(tmp_path, dataset_factory)
  meta["frames"][4]["file_path"] = "./" + meta["frames"][1]["file_path"]
  files.write_json(path, meta)
  with pytest.raises(InputError, match=r"same image as frames\[1\]\.file_path") as error:
    load_dataset(root)
  assert (error.value.path, error.value.field) == (str(path), "frames[4].file_path")


def test_a_training_frame_repeated_in_the_test_file_names_both(tmp_path, dataset_factory):
  root, path, meta = written_scene(tmp_path, dataset_factory)
  path.rename(root / "transforms_train.json")
  files.write_json(root / "transforms_test.json", dict(meta, frames=meta["frames"][2:3]))
  with pytest.raises(InputError, match=r"transforms_train.json's frames\[2\]") as error:
    load_dataset(root)
  assert error.value.path == str(root / "transforms_test.json")
  assert error.value.field == "frames[0].file_path"
  # val repeating test (instant-NGP's habit) stays accepted.
  files.write_json(root / "transforms_train.json", dict(meta, frames=meta["frames"][:3]))
  files.write_json(root / "transforms_test.json", dict(meta, frames=meta["frames"][3:]))
  files.write_json(root / "transforms_val.json", dict(meta, frames=meta["frames"][3:]))
  assert load_dataset(root, split="eval").num_images == 2


@pytest.mark.parametrize("matrix, problem", [
    ([[1, 0, 0, 0], [0, 0, 0, 0], [0, 0, 1, 0]], "singular"),
    ([[1e-30, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], "singular"),
    ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 0]], "reflection"),
    ([[1, 0.5, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], "shears"),
    ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]], "last row"),
], ids=["zero_row", "crushed_axis", "reflection", "shear", "projective"])
def test_an_applied_transform_that_is_no_similarity_is_refused(tmp_path, dataset_factory,
                                                                matrix, problem):
  root, path, meta = written_scene(tmp_path, dataset_factory)
  meta["applied_transform"] = matrix
  files.write_json(path, meta)
  with pytest.raises(InputError, match=problem) as error:
    load_dataset(root)
  assert (error.value.path, error.value.field) == (str(path), "applied_transform")


def test_a_scaled_rotation_applied_transform_is_accepted(tmp_path, dataset_factory):
  root, path, meta = written_scene(tmp_path, dataset_factory)
  rotation = poses.rotation_between([0, 0, 1], [0, 1, 0])
  meta["applied_transform"] = np.concatenate([3.0 * rotation, [[1], [2], [3]]], 1).tolist()
  files.write_json(path, meta)
  assert load_dataset(root).num_images == 4


@pytest.mark.parametrize("camera_model, key, value", [
    ("OPENCV", "k1", 1e30), ("OPENCV", "p2", -2e3), ("OPENCV_FISHEYE", "k4", 5e4),
    ("FULL_OPENCV", "k6", 1e300)])
def test_an_absurd_distortion_coefficient_is_refused(tmp_path, dataset_factory, camera_model,
                                                     key, value):
  fisheye = camera_model == "OPENCV_FISHEYE"
  root, path, meta = written_scene(tmp_path, dataset_factory, distortion=(
      (0.05, -0.01, 0.002, -0.0005) if fisheye else None), fisheye=fisheye)
  meta["camera_model"], meta[key] = camera_model, value
  files.write_json(path, meta)
  with pytest.raises(InputError, match="no real lens") as error:
    load_dataset(root)
  assert (error.value.path, error.value.field) == (str(path), key)
  meta[key] = 900.0  # Within the bound: read as given.
  meta["frames"][0][key] = value  # A per-frame value is named as such.
  files.write_json(path, meta)
  with pytest.raises(InputError) as error:
    load_dataset(root)
  assert error.value.field == f"frames[0].{key}"


@pytest.mark.parametrize("position", [1e300, -1e11])
def test_an_absurd_camera_position_names_the_frame(tmp_path, dataset_factory, position):
  root, path, meta = written_scene(tmp_path, dataset_factory)
  meta["frames"][2]["transform_matrix"][1][3] = position
  files.write_json(path, meta)
  with pytest.raises(InputError, match="camera position") as error:
    load_dataset(root)
  assert (error.value.path, error.value.field) == (str(path), "frames[2].transform_matrix")


def test_a_scene_far_from_the_origin_is_still_read(tmp_path, dataset_factory):
  root, path, meta = written_scene(tmp_path, dataset_factory)
  for frame in meta["frames"]:
    frame["transform_matrix"][0][3] += 1e5  # e.g. map coordinates in metres
  for corner in meta["signerf"]["scene_bounds"]:
    corner[0] += 1e5
  files.write_json(path, meta)
  restored = load_dataset(root, split="all")
  # The box is centred and scaled as any box outside the unit box is; the cameras keep their
  # distance to it (2.5 / 0.8 of its half-side, 1.25 / 0.8 of its height above its centre).
  np.testing.assert_allclose(restored.scene_bounds, [[-1, -1, -0.6875], [1, 1, 0.6875]])
  np.testing.assert_allclose(np.linalg.norm(restored.cameras.positions[:, :2], axis=-1),
                             2.5 / 0.8, rtol=1e-3)  # float32 steps of 0.008 at 1e5


def stationary_capture(tmp_path, dataset_factory, same_direction: bool):
  """A plain capture (no signerf block) whose cameras all stand at (1, 2, 3)."""
  root, path, meta = written_scene(tmp_path, dataset_factory, with_extras=False)
  del meta["signerf"], meta["applied_transform"]
  for frame in meta["frames"]:
    if same_direction:
      frame["transform_matrix"] = meta["frames"][0]["transform_matrix"]
    for row, value in zip(frame["transform_matrix"], (1.0, 2.0, 3.0)):
      row[3] = value
  files.write_json(path, meta)
  return root


@pytest.mark.parametrize("same_direction", [True, False], ids=["one_pose", "panorama"])
def test_cameras_that_do_not_move_ask_for_the_scene_region(tmp_path, dataset_factory,
                                                           same_direction):
  root = stationary_capture(tmp_path, dataset_factory, same_direction)
  with pytest.raises(InputError, match="cameras do not move.*--scene_center.*--scene_radius"
                     ) as error:
    load_dataset(root)
  assert error.value.path == str(root)
  # Given the region, the capture loads in it.
  given = load_dataset(root, scene_center=(1.0, 2.0, 4.0), scene_radius=2.0)
  assert given.frame["center_in_source_units"] == pytest.approx([1.0, 2.0, 4.0])
  assert given.frame["half_size_in_source_units"] == pytest.approx([2.0] * 3)
  # A radius alone centres the region on the cameras; rays start clear of the lens.
  around = load_dataset(root, scene_radius=2.0)
  assert around.frame["center_in_source_units"] == pytest.approx([1.0, 2.0, 3.0], abs=1e-5)
  assert around.near == pytest.approx(0.05)


def test_degenerate_signerf_scene_bounds_are_refused(tmp_path, dataset_factory):
  root, path, meta = written_scene(tmp_path, dataset_factory)
  for bounds in ([[0, 0, 0], [1e-300, 1e-300, 1e-300]],
                 [[5, 5, 5], [5 + 1e-9, 5 + 1e-9, 5 + 2e-9]]):
    meta["signerf"]["scene_bounds"] = bounds
    files.write_json(path, meta)
    with pytest.raises(InputError, match="degenerate") as error:
      load_dataset(root)
    assert (error.value.path, error.value.field) == (str(path), "signerf.scene_bounds")
  meta["signerf"]["scene_bounds"] = [[5, 5, 5], [5.001, 5.001, 5.001]]  # small, not degenerate
  files.write_json(path, meta)
  assert load_dataset(root).num_images == 4


def test_masks_that_ignore_every_pixel_name_the_mask_folder(tmp_path, dataset_factory):
  root, path, meta = written_scene(tmp_path, dataset_factory)
  for frame in meta["frames"]:
    files.write_image(root / frame["mask_path"], np.zeros((9, 12)))
  with pytest.raises(InputError, match="no pixel is left") as error:
    load_dataset(root, split="all")
  assert error.value.path == str(root / "masks") and error.value.field == "mask_path"
  # One pixel of one view is enough to train on (the others are still refused per split).
  mask = np.zeros((9, 12))
  mask[4, 5] = 1.0
  files.write_image(root / meta["frames"][0]["mask_path"], mask)
  assert load_dataset(root, split="all").masks.sum() > 0


def test_an_empty_held_out_split_of_the_file_s_own_blames_no_flag(tmp_path, dataset_factory):
  root, path, meta = written_scene(tmp_path, dataset_factory)
  meta["train_filenames"] = [frame["file_path"] for frame in meta["frames"]]
  files.write_json(path, meta)
  with pytest.raises(InputError, match="the dataset's own split puts none of its 5 views") as error:
    load_dataset(root, split="eval")
  assert error.value.field is None  # eval_every was never given.
  assert load_dataset(root, split="eval", eval_every=2).num_images == 3
