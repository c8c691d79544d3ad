import dataclasses

import numpy as np
import pytest

from signerf_jax import camera
from signerf_jax.errors import InputError
from signerf_jax.geometry import reference_cameras
from signerf_jax.geometry import selection

BOX = selection.Box.create([0.6, -0.4, 0.0], [1.2, 0.2, 0.5])  # off the scene centre
SELECTION = np.asarray(BOX.corners)
CENTER = np.asarray(BOX.center)
FOCAL = 150.0
Z_UP = reference_cameras.ReferencePlacement(up=(0, 0, 1))


def ring_cameras(azimuths_degrees, distance=4.0, elevation_degrees=25.0, target=None, size=64):
  """Dataset cameras on a circle around `target` (z up), all looking at it."""
  target = CENTER if target is None else np.asarray(target, np.float32)
  azimuth = np.deg2rad(np.asarray(azimuths_degrees, np.float64))
  elevation = np.deg2rad(elevation_degrees)
  offsets = np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                      np.full_like(azimuth, np.sin(elevation))], -1)
  eyes = (target + distance * offsets).astype(np.float32)
  return camera.Cameras.create(camera.look_at(eyes, np.broadcast_to(target, eyes.shape)),
                               fx=FOCAL, width=size, height=size)


def azimuth_about_z(cameras):
  offsets = np.asarray(cameras.positions) - CENTER
  return np.rad2deg(np.arctan2(offsets[:, 1], offsets[:, 0]))


def circular_gaps(degrees):
  ordered = np.sort(np.mod(degrees, 360))
  return np.diff(np.concatenate([ordered, ordered[:1] + 360]))


def test_full_circle_gives_evenly_spread_cameras_looking_at_the_selection():
  dataset = ring_cameras(np.arange(0, 360, 15))
  cameras, report = reference_cameras.place_reference_cameras(dataset, SELECTION, placement=Z_UP)
  assert cameras.num_cameras == 5
  np.testing.assert_allclose(circular_gaps(azimuth_about_z(cameras)), 72.0, atol=1e-3)
  assert report.dataset_arc_degrees == pytest.approx(345.0)
  to_center = CENTER - np.asarray(cameras.positions)
  to_center /= np.linalg.norm(to_center, axis=-1, keepdims=True)
  np.testing.assert_allclose(np.asarray(cameras.forward), to_center, atol=1e-5)
  np.testing.assert_allclose(report.elevation_degrees, 25.0, atol=1e-3)
  # The dataset distance (4) already gives a fill inside [min_fill, max_fill]: kept.
  np.testing.assert_allclose(report.distance, 4.0, rtol=1e-5)
  assert np.all((report.fill_ratio > 0.1) & (report.fill_ratio < 0.6))
  assert report.dataset_views_seeing_selection == 24


def test_partial_arc_stays_inside_the_covered_arc():
  dataset = ring_cameras(np.linspace(-40, 50, 10))
  cameras, report = reference_cameras.place_reference_cameras(dataset, SELECTION, count=3,
                                                              placement=Z_UP)
  np.testing.assert_allclose(np.sort(azimuth_about_z(cameras)), [-25.0, 5.0, 35.0], atol=1e-3)
  assert report.dataset_arc_degrees == pytest.approx(90.0)
  assert report.reference_arc_degrees == pytest.approx(60.0, abs=1e-3)


def test_elevation_follows_the_nearby_dataset_cameras():
  low = ring_cameras(np.arange(0, 180, 10), elevation_degrees=10.0)
  high = ring_cameras(np.arange(180, 360, 10), elevation_degrees=50.0)
  dataset = camera.Cameras.create(
      np.concatenate([low.camera_to_world, high.camera_to_world]), fx=FOCAL, width=64, height=64)
  cameras, report = reference_cameras.place_reference_cameras(dataset, SELECTION, count=4,
                                                              placement=Z_UP)
  azimuth = np.mod(azimuth_about_z(cameras), 360)
  # Away from the two seams, all three nearest dataset cameras share one elevation.
  away_from_seams = np.minimum(np.abs(azimuth - 180), np.minimum(azimuth, 360 - azimuth)) > 20
  assert away_from_seams.sum() >= 2
  expected = np.where(azimuth < 180, 10.0, 50.0)
  np.testing.assert_allclose(report.elevation_degrees[away_from_seams],
                             expected[away_from_seams], atol=1e-3)


def test_distant_dataset_cameras_are_brought_closer_and_near_ones_pushed_back():
  for distance, (min_fill, max_fill) in [(40.0, (0.25, 0.6)), (0.8, (0.25, 0.6))]:
    dataset = ring_cameras(np.arange(0, 360, 30), distance=distance)
    cameras, report = reference_cameras.place_reference_cameras(
        dataset, SELECTION,
        placement=dataclasses.replace(Z_UP, min_fill=min_fill, max_fill=max_fill))
    center, radius = reference_cameras.selection_sphere(SELECTION)
    # The bounding sphere's projected square covers min_fill (far) / max_fill (near) of the frame.
    half_angle = np.arcsin(radius / report.distance)
    fill = (2 * FOCAL * np.tan(half_angle))**2 / 64**2
    np.testing.assert_allclose(fill, min_fill if distance > 10 else max_fill, rtol=1e-4)
    # The selection's own box is inside its sphere, so it fills less.
    assert np.all(report.fill_ratio <= fill + 1e-6)


def test_user_given_cameras_are_described_and_checked():
  dataset = ring_cameras(np.arange(0, 360, 30))
  user = ring_cameras([10.0, 100.0], distance=3.0)
  report = reference_cameras.describe_reference_cameras(user, dataset, SELECTION, up=(0, 0, 1))
  np.testing.assert_allclose(report.azimuth_degrees - report.azimuth_degrees[0], [0.0, 90.0],
                             atol=1e-3)
  looking_away = ring_cameras([10.0], distance=3.0, target=CENTER + np.array([0, 0, 30.0]))
  with pytest.raises(InputError, match=r"reference cameras \[0\] do not see the selection"):
    reference_cameras.describe_reference_cameras(looking_away, dataset, SELECTION)


def test_degenerate_inputs_are_input_errors():
  elsewhere = ring_cameras(np.arange(0, 360, 60), target=CENTER + np.array([0, 0, 50.0]),
                           distance=2.0)
  with pytest.raises(InputError, match="none of the 6 dataset cameras sees the selection"):
    reference_cameras.place_reference_cameras(elsewhere, SELECTION)
  at_center = camera.Cameras.create(
      camera.look_at(np.repeat(CENTER[None], 2, 0), CENTER + np.array([[1.0, 0, 0], [0, 1.0, 0]])),
      fx=5.0, width=64, height=64)  # wide angle: they see the selection's corners
  with pytest.raises(InputError, match="sits at its centre"):
    reference_cameras.place_reference_cameras(at_center, SELECTION)


def test_report_is_json_friendly():
  dataset = ring_cameras(np.arange(0, 360, 45))
  _, report = reference_cameras.place_reference_cameras(dataset, SELECTION)
  summary = report.to_json()
  assert len(summary["fill_ratio"]) == 5 and isinstance(summary["dataset_arc_degrees"], float)


@pytest.mark.parametrize("fields, field", [
    ({"min_fill": 0.7, "max_fill": 0.6}, "ReferencePlacement.min_fill"),
    ({"max_fill": 1.0}, "ReferencePlacement.max_fill"),
    ({"neighbours": 0}, "ReferencePlacement.neighbours"),
])
def test_bad_placement_is_an_input_error_naming_the_field(fields, field):
  with pytest.raises(InputError) as error:
    reference_cameras.ReferencePlacement(**fields)
  assert error.value.field == field
