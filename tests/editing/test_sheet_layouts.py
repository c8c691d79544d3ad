"""experiments/sheet_layouts.py: an edit's reference views painted as sheets and alone, measured
inside their masks. A stand-in generator paints each sample's mask one colour, so the measures
have known values."""

import argparse

import numpy as np
import pytest

SIZE = 8


@pytest.fixture(scope="module")
def experiment(experiment_script):
  return experiment_script("sheet_layouts")


class OneColourPerSample:
  """Paints a sample's mask (>= 0.5) in one colour: red, or drawn from the sample's key."""

  batch_size = 2

  def __init__(self, colour_from_key: bool):
    self.colour_from_key = colour_from_key

  def __call__(self, image, mask, control, keys):
    del control
    colours = [np.random.default_rng(list(map(int, key))).uniform(size=3) if self.colour_from_key
               else np.array([1.0, 0.0, 0.0]) for key in keys]
    return np.stack([np.where(one_mask >= 0.5, colour, one_image)
                     for one_image, one_mask, colour in zip(image, mask, colours)])


def reference_tiles(count: int = 5) -> dict[str, np.ndarray]:
  """Grey renders with a centred square mask (16 of 64 pixels)."""
  mask = np.zeros((count, SIZE, SIZE), np.float32)
  mask[:, 2:6, 2:6] = 1.0
  return {"render": np.full((count, SIZE, SIZE, 3), 0.5, np.float32),
          "control": np.zeros((count, SIZE, SIZE), np.float32), "mask": mask}


@pytest.mark.parametrize("rows, columns, views_per_seed", [(2, 3, 5), (2, 2, 6), (1, 2, 5)])
def test_every_reference_view_is_painted_in_each_layout(experiment, rows, columns,
                                                        views_per_seed):
  tiles = reference_tiles()
  groups, first = experiment.paint_sheets(OneColourPerSample(False), tiles, rows, columns,
                                          [0, 1])
  measures = experiment.summarize(groups)
  assert measures["views"] == 2 * views_per_seed
  assert measures["changed"] == 1.0
  assert measures["difference"] == pytest.approx(0.5)
  assert measures["chroma"] == pytest.approx(1.0)
  np.testing.assert_allclose(first[:, 3, 3], [[1.0, 0.0, 0.0]] * 5)  # Each view, painted.
  np.testing.assert_allclose(first[:, 0, 0], 0.5)  # Outside the mask, the render.


def test_colour_spread_separates_views_painted_together_from_views_painted_alone(experiment):
  tiles, generator = reference_tiles(), OneColourPerSample(True)
  sheet = experiment.summarize(experiment.paint_sheets(generator, tiles, 2, 3, [0, 1, 2])[0])
  alone = experiment.summarize(experiment.paint_singles(generator, tiles, [0, 1, 2])[0])
  assert sheet["colour_spread"] == pytest.approx(0.0)  # One sample: one colour for its tiles.
  assert alone["colour_spread"] > 0.1  # A key per view: a colour per view.
  assert sheet["views"] == alone["views"] == 15


def test_a_sheet_of_one_tile_has_no_spread(experiment):
  groups, _ = experiment.paint_sheets(OneColourPerSample(True), reference_tiles(), 1, 2, [0])
  assert experiment.summarize(groups)["colour_spread"] is None


def test_view_measures_of_an_unchanged_and_a_grey_view(experiment):
  tiles = reference_tiles(1)
  render, mask = tiles["render"][0], tiles["mask"][0]
  share, difference, chroma, colour = experiment.view_measures(render, render, mask)
  assert (share, difference) == (0.0, 0.0) and np.isnan(chroma) and np.isnan(colour).all()
  grey = np.where(mask[..., None] >= 0.5, 0.9, render)
  assert experiment.view_measures(grey, render, mask)[:3] == pytest.approx((1.0, 0.4, 0.0))
  with pytest.raises(ValueError, match="empty mask"):
    experiment.view_measures(render, render, np.zeros_like(mask))


@pytest.mark.parametrize("text", ["1x1", "2by3", "x2", "0x5"])
def test_bad_layouts_are_refused(experiment, text):
  with pytest.raises(argparse.ArgumentTypeError, match="ROWSxCOLUMNS"):
    experiment.parse_layout(text)
  assert experiment.parse_layout("2x3") == (2, 3)
