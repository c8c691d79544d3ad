import numpy as np
import pytest

from signerf_jax import camera
from signerf_jax.editing import crops
from signerf_jax.geometry import selection

WIDTH, HEIGHT = 96, 64


def cameras_looking_at(targets, eyes):
  return camera.Cameras.create(camera.look_at(np.asarray(eyes, np.float32),
                                              np.asarray(targets, np.float32)),
                               fx=80.0, width=WIDTH, height=HEIGHT)


def test_crop_box_holds_the_selection_with_margin_at_the_tile_aspect():
  box = selection.Box.create([-0.2, -0.2, -0.2], [0.2, 0.2, 0.2])
  # Looking past the box: it projects off-centre but inside the frame.
  cameras = cameras_looking_at([[0.4, 0.0, 0.3]], [[4.0, 0.0, 0.5]])
  boxes = np.asarray(crops.selection_crop_boxes(cameras, box.corners, 32, 48, margin=0.1,
                                                max_upscale=100.0))
  pixels, _ = camera.project(cameras, box.corners)
  low, high = np.asarray(pixels[0]).min(0), np.asarray(pixels[0]).max(0)
  x0, y0, width, height = boxes[0]
  assert width / height == pytest.approx(48 / 32)
  assert x0 <= low[0] and y0 <= low[1] and x0 + width >= high[0] and y0 + height >= high[1]
  assert x0 >= 0 and y0 >= 0 and x0 + width <= WIDTH and y0 + height <= HEIGHT
  # The limiting side gets exactly the margin.
  extent = high - low
  assert max(width, height * 48 / 32) == pytest.approx(
      max(extent[0], extent[1] * 48 / 32) * 1.2, rel=1e-4)
  # By default a small selection is not magnified more than twice.
  default = np.asarray(crops.selection_crop_boxes(cameras, box.corners, 32, 48))
  assert default[0, 2] == pytest.approx(24.0)


def test_crop_box_near_the_border_is_shifted_inside_and_oversized_boxes_are_centred():
  box = selection.Box.create([-0.2, -0.2, -0.2], [0.2, 0.2, 0.2])
  cameras = cameras_looking_at([[0.0, 2.3, 0.0], [0.0, 0.0, 0.0]], [[4.0, 0.0, 0.0],
                                                                     [0.45, 0.0, 0.0]])
  boxes = np.asarray(crops.selection_crop_boxes(cameras, box.corners, 32, 32))
  x0, y0, width, height = boxes[0]
  assert x0 == pytest.approx(0.0, abs=1e-4)  # clamped to the left border
  x0, y0, width, height = boxes[1]  # very close: larger than the frame
  assert width > WIDTH and height > HEIGHT
  assert x0 + width / 2 == pytest.approx(WIDTH / 2) and y0 + height / 2 == pytest.approx(
      HEIGHT / 2)


def test_camera_inside_the_selection_gets_the_full_frame():
  box = selection.Box.create([-1.0, -1.0, -1.0], [1.0, 1.0, 1.0])
  cameras = cameras_looking_at([[1.0, 0.0, 0.0]], [[0.0, 0.0, 0.0]])
  boxes = np.asarray(crops.selection_crop_boxes(cameras, box.corners, 32, 32))
  np.testing.assert_allclose(boxes[0], [0.0, -16.0, 96.0, 96.0])
  np.testing.assert_allclose(crops.full_frame_boxes(1, HEIGHT, WIDTH, 32, 32), boxes)


def test_identity_crop_and_letterbox_fill():
  rng = np.random.default_rng(0)
  images = rng.random((2, HEIGHT, WIDTH, 3)).astype(np.float32)
  same = crops.crop_to_tiles(images, np.tile([[0.0, 0.0, WIDTH, HEIGHT]], (2, 1)), HEIGHT, WIDTH)
  np.testing.assert_allclose(same, images, atol=1e-6)
  boxes = crops.full_frame_boxes(2, HEIGHT, WIDTH, 48, 48)
  tiles = np.asarray(crops.crop_to_tiles(images, boxes, 48, 48, fill_value=0.25))
  np.testing.assert_array_equal(tiles[:, :8], 0.25)  # 16 rows of padding -> 8 tile rows
  np.testing.assert_array_equal(tiles[:, -8:], 0.25)
  assert not np.any(tiles[:, 8:-8] == 0.25)


def test_paste_changes_only_masked_pixels():
  rng = np.random.default_rng(1)
  images = rng.random((2, HEIGHT, WIDTH, 3)).astype(np.float32)
  boxes = np.array([[10.0, 4.0, 48.0, 32.0], [40.0, 20.0, 60.0, 40.0]], np.float32)
  masks = np.zeros((2, HEIGHT, WIDTH), np.float32)
  masks[0, 10:30, 20:50] = 1.0
  masks[1, 30:50, 60:90] = 0.5
  masks[1, 0:5, 0:5] = 1.0  # outside its crop: cannot change
  edited_tiles = np.ones((2, 32, 48, 3), np.float32)
  pasted = np.asarray(crops.paste_tiles(images, edited_tiles, boxes, masks))
  unchanged = masks == 0
  unchanged[1, 0:5, 0:5] = True
  np.testing.assert_array_equal(pasted[unchanged], images[unchanged])  # bit for bit
  np.testing.assert_allclose(pasted[0, 10:30, 20:50], 1.0, atol=1e-6)
  np.testing.assert_allclose(pasted[1, 30:50, 60:90], 0.5 * images[1, 30:50, 60:90] + 0.5,
                             atol=1e-6)


def test_crop_then_paste_round_trip_is_close():
  rows, columns = np.mgrid[:HEIGHT, :WIDTH]
  smooth = np.stack([np.sin(rows / 9.0), np.cos(columns / 7.0), rows * columns / 6144.0], -1)
  images = smooth[None].astype(np.float32)
  boxes = np.array([[20.0, 10.0, 40.0, 40.0]], np.float32)
  tiles = crops.crop_to_tiles(images, boxes, 80, 80)  # upsampled twice
  masks = np.zeros((1, HEIGHT, WIDTH), np.float32)
  masks[0, 15:45, 25:55] = 1.0
  pasted = np.asarray(crops.paste_tiles(images, tiles, boxes, masks))
  np.testing.assert_allclose(pasted, images, atol=0.02)
