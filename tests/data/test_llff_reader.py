import numpy as np
import pytest

from signerf_jax import camera, files
from signerf_jax.data import load_dataset, poses
from signerf_jax.errors import InputError

HEIGHT, WIDTH, FOCAL = 12, 16, 14.0


def opengl_cameras(count=9):
  """Forward-facing cameras on a small grid, looking at a point 5 units in front (-z)."""
  offsets = np.stack(np.meshgrid(np.linspace(-0.5, 0.5, 3), np.linspace(-0.3, 0.3, 3)),
                     -1).reshape(-1, 2)[:count]
  eyes = np.concatenate([offsets, np.zeros((count, 1))], -1).astype(np.float32)
  return np.asarray(camera.look_at(eyes, np.array([0.0, 0.0, -5.0], np.float32), (0, 1, 0)))


def write_llff_scene(root, camera_to_world, folders=(2,)):
  """poses_bounds.npy in LLFF's convention and images_N folders (view i is filled with i/20)."""
  right, up, back, position = np.moveaxis(camera_to_world, -1, 0)
  # LLFF's columns are [down, right, backwards].
  llff = np.stack([-up, right, back, position,
                   np.broadcast_to([HEIGHT, WIDTH, FOCAL], right.shape)], -1)
  bounds = np.broadcast_to([3.0, 8.0], (len(llff), 2))
  np.save(root / "poses_bounds.npy", np.concatenate([llff.reshape(-1, 15), bounds], -1))
  for factor in folders:
    for index in range(len(llff)):
      image = np.full((HEIGHT // factor, WIDTH // factor, 3), index / 20, np.float32)
      files.write_image(root / f"images_{factor}" / f"IMG_{9000 + index}.png", image)


def test_llff_reader_converts_axes_normalises_and_scales_focal(tmp_path):
  camera_to_world = opengl_cameras()
  write_llff_scene(tmp_path, camera_to_world)
  dataset = load_dataset(tmp_path, split="all", downscale=2)
  assert dataset.scene_kind == "forward_facing" and dataset.background_color is None
  assert (dataset.width, dataset.height) == (8, 6)
  np.testing.assert_allclose(dataset.cameras.fx, FOCAL / 2)
  np.testing.assert_allclose(dataset.cameras.cx, 4.0)
  expected = poses.transform_poses(dataset.world_from_source, camera_to_world)
  np.testing.assert_allclose(dataset.cameras.camera_to_world, expected, atol=1e-5)
  # Images come in sorted order, one per row.
  np.testing.assert_allclose(dataset.images[:, 0, 0, 0], np.arange(9) / 20, atol=1 / 255)
  # Recentred: the mean camera looks down -z from the top of the unit box.
  np.testing.assert_allclose(np.mean(dataset.cameras.forward, 0), [0, 0, -1], atol=0.05)
  lower, upper = dataset.scene_bounds
  assert np.max(upper - lower) == pytest.approx(2.0) and np.all(lower >= -1) and np.all(upper <= 1)
  # The content (between near 3 and far 8 in front of every camera) is inside the bounds.
  scale = poses.similarity_scale(dataset.world_from_source)
  target = poses.transform_points(dataset.world_from_source, [[0.0, 0.0, -5.0]])[0]
  assert np.all((target > lower) & (target < upper))
  assert dataset.near == pytest.approx(3 * scale)
  assert dataset.far > 8 * scale


def test_llff_downscale_falls_back_to_a_finer_folder_and_splits_like_nerf(tmp_path):
  write_llff_scene(tmp_path, opengl_cameras(), folders=(2,))
  held_out = load_dataset(tmp_path, split="eval", downscale=4, eval_every=8)
  assert held_out.image_names == ("images_2/IMG_9000.png", "images_2/IMG_9008.png")
  assert (held_out.width, held_out.height) == (4, 3)
  np.testing.assert_allclose(held_out.cameras.fx, FOCAL / 4)
  assert load_dataset(tmp_path, downscale=2).num_images == 7
  with pytest.raises(InputError, match="images_2") as error:
    load_dataset(tmp_path, downscale=3)
  assert error.value.field == "downscale"


@pytest.mark.parametrize("mutate, field", [
    (lambda rows: rows.__setitem__((4, 14), 0.0), "poses_bounds[4].focal"),
    (lambda rows: rows.__setitem__((2, slice(0, 3)), rows[2, :3] * 1.1),
     "poses_bounds[2].pose"),
    (lambda rows: rows.__setitem__((3, 3), np.nan), "poses_bounds[3].pose"),
    (lambda rows: rows.__setitem__((1, 15), -1.0), "poses_bounds[1].bounds"),
    (lambda rows: rows.__setitem__((5, 9), WIDTH * 2), "poses_bounds[5].hwf"),
])
def test_llff_bad_rows_name_the_row(tmp_path, mutate, field):
  write_llff_scene(tmp_path, opengl_cameras())
  rows = np.load(tmp_path / "poses_bounds.npy")
  mutate(rows)
  np.save(tmp_path / "poses_bounds.npy", rows)
  with pytest.raises(InputError) as error:
    load_dataset(tmp_path, downscale=2)
  assert error.value.path.endswith("poses_bounds.npy") and error.value.field == field


def test_llff_wrong_array_shape_or_image_count(tmp_path):
  write_llff_scene(tmp_path, opengl_cameras())
  (tmp_path / "images_2" / "IMG_9003.png").unlink()
  with pytest.raises(InputError, match="holds 8 images but poses_bounds.npy has 9 rows"):
    load_dataset(tmp_path, downscale=2)
  np.save(tmp_path / "poses_bounds.npy", np.zeros((9, 15)))
  with pytest.raises(InputError, match=r"\[N, 17\]"):
    load_dataset(tmp_path, downscale=2)


def read_colmap_points(path):
  """xyz [P, 3] of a COLMAP points3D.bin (id, xyz, rgb, error, track)."""
  data = path.read_bytes()
  count, offset, points = int(np.frombuffer(data, np.uint64, 1)[0]), 8, []
  for _ in range(count):
    points.append(np.frombuffer(data, np.float64, 3, offset + 8))
    track_length = int(np.frombuffer(data, np.uint64, 1, offset + 43)[0])
    offset += 51 + 8 * track_length
  return np.stack(points)


@pytest.mark.shared_data
def test_fern_focal_and_colmap_points_land_in_the_images(shared_data):
  root = shared_data / "llff" / "fern"
  fern = load_dataset(root, split="all", downscale=8)
  assert (fern.width, fern.height, fern.num_images) == (504, 378, 20)
  np.testing.assert_allclose(fern.cameras.fx, 407.6, atol=0.1)
  points = poses.transform_points(fern.world_from_source,
                                  read_colmap_points(root / "sparse" / "0" / "points3D.bin"))
  lower, upper = fern.scene_bounds
  assert np.mean(np.all((points >= lower) & (points <= upper), -1)) > 0.99
  pixels, depth = camera.project(fern.cameras, points)
  pixels, depth = np.asarray(pixels), np.asarray(depth)
  inside = ((depth > 0) & (pixels[..., 0] >= 0) & (pixels[..., 0] < fern.width)
            & (pixels[..., 1] >= 0) & (pixels[..., 1] < fern.height))
  assert np.all(np.mean(inside, axis=1) > 0.9)  # per camera

  coarse = load_dataset(root, split="eval", downscale=16)
  assert coarse.image_names == ("images_16/IMG_4026.png", "images_16/IMG_4034.png",
                                "images_16/IMG_4042.png")
  assert (coarse.width, coarse.height) == (252, 189)
  np.testing.assert_allclose(coarse.cameras.fx, 407.6 / 2, atol=0.05)
  np.testing.assert_allclose(coarse.cameras.camera_to_world, fern.cameras.camera_to_world[::8],
                             atol=1e-6)


@pytest.mark.filterwarnings("error")  # A ComplexWarning would mean the values were cast.
@pytest.mark.parametrize("convert", [
    lambda rows: rows + 1e-3j,
    lambda rows: rows.astype(str),
    lambda rows: np.where(np.arange(rows.size).reshape(rows.shape) == 20, "n/a", rows),
    lambda rows: rows.astype(np.int64),
    lambda rows: rows > 0,
], ids=["complex", "text", "a_string_entry", "integer", "bool"])
def test_llff_poses_that_are_not_floating_point_name_the_file_and_the_dtype(tmp_path, convert):
  write_llff_scene(tmp_path, opengl_cameras())
  rows = convert(np.load(tmp_path / "poses_bounds.npy"))
  np.save(tmp_path / "poses_bounds.npy", rows)
  with pytest.raises(InputError, match=f"floating-point numbers, got dtype {rows.dtype}") as error:
    load_dataset(tmp_path, downscale=2)
  assert error.value.path == str(tmp_path / "poses_bounds.npy") and error.value.field == "dtype"


def test_llff_poses_saved_as_an_npz_archive_are_refused(tmp_path):
  write_llff_scene(tmp_path, opengl_cameras())
  rows = np.load(tmp_path / "poses_bounds.npy")
  with open(tmp_path / "poses_bounds.npy", "wb") as handle:
    np.savez(handle, poses_bounds=rows)
  with pytest.raises(InputError, match="is an .npz archive") as error:
    load_dataset(tmp_path, downscale=2)
  assert error.value.path == str(tmp_path / "poses_bounds.npy")
