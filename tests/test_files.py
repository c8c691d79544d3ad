import struct
import zlib

import numpy as np
import pytest

from signerf_jax import files
from signerf_jax.errors import InputError


def test_atomic_path_leaves_nothing_when_the_writer_fails(tmp_path):
  target = tmp_path / "out" / "result.json"
  files.write_json(target, {"kept": 1})
  with pytest.raises(RuntimeError):
    with files.atomic_path(target) as temporary:
      temporary.write_text("half written")
      raise RuntimeError("interrupted")
  assert files.read_json(target) == {"kept": 1}
  assert sorted(p.name for p in target.parent.iterdir()) == ["result.json"]


def test_atomic_writes_get_ordinary_file_permissions(tmp_path):
  files.write_text(tmp_path / "note.txt", "hello")
  (tmp_path / "plain.txt").write_text("hello")
  assert (tmp_path / "note.txt").stat().st_mode == (tmp_path / "plain.txt").stat().st_mode


@pytest.mark.parametrize("channels", [1, 3, 4])
@pytest.mark.parametrize("bit_depth", [8, 16])
def test_image_round_trip(tmp_path, channels, bit_depth):
  image = np.random.default_rng(0).random((7, 9, channels)).astype(np.float32)
  files.write_image(tmp_path / "image.png", image, bit_depth=bit_depth)
  restored = files.read_image(tmp_path / "image.png")
  assert restored.shape == image.shape and restored.dtype == np.float32
  np.testing.assert_allclose(restored, image, atol=0.5 / (2**bit_depth - 1) + 1e-6)


@pytest.mark.parametrize("shape", [(5, 6), (5, 6, 3)])
def test_exr_round_trip_is_exact(tmp_path, shape):
  array = np.random.default_rng(1).random(shape).astype(np.float32) * 100
  files.write_exr(tmp_path / "depth.exr", array)
  np.testing.assert_array_equal(files.read_exr(tmp_path / "depth.exr"), array)


def test_bad_files_name_themselves(tmp_path):
  broken = tmp_path / "broken.json"
  broken.write_text("{not json")
  with pytest.raises(InputError, match="broken.json"):
    files.read_json(broken)
  with pytest.raises(InputError, match="missing.png"):
    files.read_image(tmp_path / "missing.png")
  (tmp_path / "garbage.png").write_bytes(b"not an image")
  with pytest.raises(InputError, match="garbage.png"):
    files.read_image(tmp_path / "garbage.png")
  (tmp_path / "garbage.exr").write_bytes(b"not an exr")
  with pytest.raises(InputError, match="garbage.exr"):
    files.read_exr(tmp_path / "garbage.exr")


def _png_header_only(width: int, height: int) -> bytes:
  """A PNG whose IHDR claims width x height, with no pixel data (a decompression bomb's
  header costs nothing to write)."""
  ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
  chunk = lambda kind, body: (struct.pack(">I", len(body)) + kind + body
                              + struct.pack(">I", zlib.crc32(kind + body)))
  return files.PNG_SIGNATURE + chunk(b"IHDR", ihdr) + chunk(b"IEND", b"")


def test_an_oversized_image_is_refused_from_its_header(tmp_path, monkeypatch):
  path = tmp_path / "bomb.png"
  path.write_bytes(_png_header_only(100_000, 100_000))
  decoded = []
  monkeypatch.setattr(files.cv2, "imdecode", lambda *args: decoded.append(args))
  with pytest.raises(InputError, match="100000x100000 pixels is more than") as error:
    files.read_image(path)
  assert error.value.path == str(path) and decoded == []  # Nothing was decoded.


@pytest.mark.parametrize("suffix", [".png", ".jpg"])
@pytest.mark.parametrize("kept", [0.5, 0.9, 0.999])
def test_a_truncated_image_is_an_error_never_a_grey_image(tmp_path, suffix, kept):
  image = np.random.default_rng(0).random((64, 48, 3)).astype(np.float32)
  whole = tmp_path / f"whole{suffix}"
  files.write_image(whole, image)
  data = whole.read_bytes()
  cut = tmp_path / f"cut{suffix}"
  cut.write_bytes(data[:int(len(data) * kept)])
  with pytest.raises(InputError, match="truncated|not a readable image") as error:
    files.read_image(cut)
  assert error.value.path == str(cut)
  assert files.read_image(whole).shape == (64, 48, 3)


@pytest.mark.parametrize("contents", [b"", b"not an image at all", files.PNG_SIGNATURE + b"x",
                                      files.JPEG_START + b"\xff\xe0\x00"],
                         ids=["empty", "text", "png_signature_only", "jpeg_start_only"])
def test_garbage_is_not_a_readable_image(tmp_path, contents):
  path = tmp_path / "image.png"
  path.write_bytes(contents)
  with pytest.raises(InputError, match="not a readable image|truncated"):
    files.read_image(path)
