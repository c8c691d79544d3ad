import dataclasses
import json

import numpy as np
import pytest

from signerf_jax.errors import InputError
from signerf_jax.nerf import capacity, scene_info
from signerf_jax.nerf import model as nerf_model
from signerf_jax.nerf.encoding import grid_layout
from signerf_jax.nerf.perspective_warp import PerspectiveWarp

LEGO_100 = scene_info.SceneInfo(bounds=((-1, -1, -1), (1, 1, 1)), kind="bounded", near=1.0,
                              far=4.4, background_color=(1, 1, 1), num_images=100, width=100,
                              height=100, pixel_footprint=2.7 / 138.9, camera_distance=2.7)


def test_bounded_scene_gets_an_occupancy_grid_no_contraction_and_its_background():
  derived = capacity.derive_capacity(LEGO_100)
  assert derived.sampler == "occupancy" and not derived.contract
  assert derived.background == "constant" and not derived.appearance_embedding
  # ~one finest cell per pixel footprint: 2 / 0.0194 ~ 103 cells.
  assert 96 <= derived.finest_resolution <= 112


def test_table_never_exceeds_the_finest_levels_vertices_and_grows_with_resolution():
  small = capacity.derive_capacity(LEGO_100)
  large = capacity.derive_capacity(dataclasses.replace(LEGO_100, width=800, height=800,
                                                       pixel_footprint=2.7 / 1111))
  assert large.finest_resolution >= 7 * small.finest_resolution
  assert large.log2_table_size > small.log2_table_size
  assert large.num_levels > small.num_levels and large.march_steps > small.march_steps
  for derived in (small, large):
    assert 2**derived.log2_table_size <= (derived.finest_resolution + 1)**3
    layout = grid_layout(derived.num_levels, derived.base_resolution, derived.finest_resolution,
                         derived.log2_table_size, derived.features_per_level)
    assert layout.num_rows < 16 * 2**19  # far below the fixed large configuration


# A forward-facing scene seen through image-plane ranges of 1.6 x 1.2 (tangent units).
FORWARD_FACING = dataclasses.replace(
    LEGO_100, kind="forward_facing", background_color=None,
    perspective=PerspectiveWarp((0.0, 0.0, 1.0), ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0),
                                                  (0.0, 0.0, 1.0)),
                                (-0.8, -0.6, 0.5), (0.8, 0.6, 4.5)))


@pytest.mark.parametrize("kind, contract", [("forward_facing", False), ("unbounded", True)])
def test_real_scenes_use_proposals_and_contract_only_when_unbounded(kind, contract):
  scene = (FORWARD_FACING if kind == "forward_facing"
           else dataclasses.replace(LEGO_100, kind=kind, background_color=None))
  derived = capacity.derive_capacity(scene)
  assert derived.sampler == "proposal" and derived.contract == contract
  assert derived.perspective_warp == (kind == "forward_facing")
  assert derived.background == "last_sample" and not derived.appearance_embedding
  if contract:  # the inner box takes half of the contracted grid
    assert derived.finest_resolution >= 2 * capacity.derive_capacity(LEGO_100).finest_resolution - 8


@pytest.mark.parametrize("kind", ["bounded", "forward_facing", "unbounded"])
def test_field_coordinates_map_back_to_the_scene_points(kind):
  scene = {"bounded": LEGO_100, "forward_facing": FORWARD_FACING,
           "unbounded": dataclasses.replace(LEGO_100, kind=kind, background_color=None)}[kind]
  model = nerf_model.NerfModel(scene, capacity.derive_capacity(scene))
  # Inside the box, far outside it (contracted) and in front of the forward-facing cameras.
  points = np.array([[0.2, -0.5, -1.5], [0.9, 0.3, -2.0], [-0.1, 0.1, -2.5]], np.float32)
  if kind == "unbounded":
    points = np.concatenate([points, [[30.0, -4.0, 2.0]]]).astype(np.float32)
  coordinates = model.to_unit_cube(points)
  np.testing.assert_allclose(model.from_unit_cube(coordinates), points, rtol=1e-4, atol=1e-5)


def test_overrides_pin_fields_and_bad_footprint_is_an_input_error():
  pinned = capacity.derive_capacity(LEGO_100, capacity.CapacityRules(overrides={
      "finest_resolution": 2048, "log2_table_size": 19}))
  assert (pinned.finest_resolution, pinned.log2_table_size) == (2048, 19)
  with pytest.raises(InputError, match="pixel footprint"):
    capacity.derive_capacity(dataclasses.replace(LEGO_100, pixel_footprint=0.0))


@pytest.mark.parametrize("fields, field", [
    ({"overrides": {"finest_resolutoin": 64}}, "CapacityRules.overrides"),
    ({"level_growth": 1.0}, "CapacityRules.level_growth"),
    ({"render_sample_fraction": 0.0}, "CapacityRules.render_sample_fraction"),
    ({"render_sample_fraction": 1.5}, "CapacityRules.render_sample_fraction"),
])
def test_bad_rules_are_input_errors_naming_the_field(fields, field):
  with pytest.raises(InputError) as error:
    capacity.CapacityRules(**fields)
  assert error.value.field == field


def test_json_round_trip():
  derived = capacity.derive_capacity(LEGO_100)
  assert capacity.Capacity.from_json(dataclasses.asdict(derived)) == derived
  assert scene_info.SceneInfo.from_json(dataclasses.asdict(LEGO_100)) == dataclasses.replace(
      LEGO_100, bounds=((-1.0,) * 3, (1.0,) * 3), background_color=(1, 1, 1))
  as_json = json.loads(json.dumps(dataclasses.asdict(FORWARD_FACING)))
  assert scene_info.SceneInfo.from_json(as_json).perspective == FORWARD_FACING.perspective


def test_a_model_json_with_removed_options_loads_only_at_their_remaining_value():
  derived = capacity.derive_capacity(LEGO_100)
  older = {**dataclasses.asdict(derived), "hashed": True, "pose_refinement": False}
  assert capacity.Capacity.from_json(older) == derived
  for name, value in [("pose_refinement", True), ("hashed", False)]:
    with pytest.raises(InputError, match=f"{name} = {value}.*no longer") as error:
      capacity.Capacity.from_json({**older, name: value})
    assert error.value.field == f"capacity.{name}"
  with pytest.raises(InputError, match=r"not fields of Capacity: \['pose_refinement'\]"):
    capacity.CapacityRules(overrides={"pose_refinement": True})


def test_rendering_takes_its_fraction_of_the_field_samples_and_training_all():
  derived = dataclasses.replace(capacity.derive_capacity(FORWARD_FACING),
                                proposal_samples=(48, 24), samples_per_ray=24)
  # The proposal networks keep every sample; the field's count is a multiple of 4, at least 4.
  for fraction, rendering in [(1.0, ((48, 24), 24)), (2 / 3, ((48, 24), 16)),
                              (0.5, ((48, 24), 12)), (1 / 3, ((48, 24), 8)),
                              (0.01, ((48, 24), 4))]:
    fractional = dataclasses.replace(derived, render_sample_fraction=fraction)
    assert fractional.sample_counts(training=True) == ((48, 24), 24)
    assert fractional.sample_counts(training=False) == rendering
  # Rendering takes every sample unless asked: with one proposal network two thirds cost 0.5 dB.
  assert capacity.derive_capacity(FORWARD_FACING).render_sample_fraction == 1.0
  assert capacity.derive_capacity(FORWARD_FACING, capacity.CapacityRules(
      render_sample_fraction=0.5)).render_sample_fraction == 0.5
  assert "(48 > 24 > 24 samples per ray; 48 > 24 > 16 when rendering)" in capacity.describe(
      dataclasses.replace(derived, render_sample_fraction=2 / 3))
  # A model saved before the fraction existed renders with every sample.
  older = {name: value for name, value in dataclasses.asdict(derived).items()
           if name != "render_sample_fraction"}
  assert capacity.Capacity.from_json(older).render_sample_fraction == 1.0


@pytest.mark.slow
@pytest.mark.shared_data
def test_capacity_of_the_benchmark_scenes(shared_data):
  from signerf_jax.data import load_dataset  # pylint: disable=g-import-not-at-top

  lego = scene_info.SceneInfo.from_dataset(
      load_dataset(shared_data / "nerf_synthetic" / "lego", downscale=8))
  derived = capacity.derive_capacity(lego)
  assert (lego.width, lego.height) == (100, 100) and derived.sampler == "occupancy"
  assert 64 <= derived.finest_resolution <= 160 and derived.log2_table_size <= 17
  fern = scene_info.SceneInfo.from_dataset(load_dataset(shared_data / "llff" / "fern",
                                                      downscale=16))
  derived = capacity.derive_capacity(fern)
  assert fern.kind == "forward_facing" and derived.sampler == "proposal"
  assert not derived.contract and not derived.appearance_embedding and derived.perspective_warp
  assert (derived.samples_per_ray, derived.rays_per_batch) == (24, 1280)


@pytest.mark.parametrize("width, unbounded_samples, unbounded_rays", [
    (100, 16, 2048), (200, 24, 1280), (504, 48, 512), (2000, 48, 512)])
def test_proposal_scenes_take_one_proposal_network_and_half_the_budget(width, unbounded_samples,
                                                                       unbounded_rays):
  forward_facing = capacity.derive_capacity(dataclasses.replace(FORWARD_FACING, width=width,
                                                                height=width * 3 // 4))
  assert (forward_facing.proposal_samples, forward_facing.samples_per_ray) == ((48,), 24)
  assert forward_facing.rays_per_batch == 1280  # 65,536 / 2 / 24, in multiples of 256
  # 360-degree captures take more samples for larger images (stitch 200^2: 48 > 24, 1,280 rays).
  unbounded = capacity.derive_capacity(dataclasses.replace(
      LEGO_100, kind="unbounded", background_color=None, width=width, height=width * 3 // 4))
  assert unbounded.proposal_samples == (2 * unbounded_samples,)
  assert (unbounded.samples_per_ray, unbounded.rays_per_batch) == (unbounded_samples,
                                                                   unbounded_rays)
  # The occupancy sampler's rays fill the whole budget at ~8 occupied samples a ray.
  assert capacity.derive_capacity(LEGO_100).rays_per_batch == 8192


def test_appearance_codes_only_when_asked_for():
  unbounded = dataclasses.replace(LEGO_100, kind="unbounded", background_color=None)
  assert not capacity.derive_capacity(unbounded).appearance_embedding
  assert capacity.derive_capacity(
      unbounded, capacity.CapacityRules(appearance_embedding=True)).appearance_embedding


def test_real_captures_get_near_camera_gradient_scaling_and_it_is_described():
  real = capacity.derive_capacity(dataclasses.replace(LEGO_100, kind="unbounded",
                                                      background_color=None),
                                  capacity.CapacityRules(appearance_embedding=True))
  synthetic = capacity.derive_capacity(LEGO_100)
  forward_facing = capacity.derive_capacity(dataclasses.replace(LEGO_100, kind="forward_facing",
                                                                background_color=None))
  assert real.near_gradient_scaling and not synthetic.near_gradient_scaling
  assert not forward_facing.near_gradient_scaling
  line = capacity.describe(real)
  assert "near-camera gradient scaling" in line and "contracted unbounded space" in line
  assert "proposal sampling" in line and "appearance codes" in line
  assert "occupancy-grid sampling" in capacity.describe(synthetic)


@pytest.mark.parametrize("views, sparse", [(1, True), (12, True), (15, True), (16, False),
                                          (100, False)])
def test_sparse_objects_model_a_pixel_as_several_rays_less_view_dependence_coarse_first(
    views, sparse):
  scene = dataclasses.replace(LEGO_100, num_images=views)
  derived = capacity.derive_capacity(scene)
  assert derived.pixel_samples == (2 if sparse else 1)
  assert derived.sh_degree == (capacity.SPARSE_SH_DEGREE if sparse else capacity.SH_DEGREE)
  assert derived.coarse_to_fine == (capacity.SPARSE_COARSE_TO_FINE if sparse else 0.0)
  assert capacity.SPARSE_SH_DEGREE < capacity.SH_DEGREE
  assert nerf_model.NerfModel(scene, derived).field.sh_degree == derived.sh_degree
  line = capacity.describe(derived)
  for words in ("rays a pixel", "spherical-harmonics degree", "coarse-to-fine"):
    assert (words in line) == sparse
  for pinned in (1, 3):
    pinned_rules = capacity.CapacityRules(pixel_samples=pinned, sh_degree=pinned,
                                          coarse_to_fine=pinned / 4)
    pinned_capacity = capacity.derive_capacity(scene, pinned_rules)
    assert (pinned_capacity.pixel_samples, pinned_capacity.sh_degree,
            pinned_capacity.coarse_to_fine) == (pinned, pinned, pinned / 4)
  # Not for unbounded or forward-facing captures (measured worse, or no better, on a real
  # 360-degree one).
  for kind in ("unbounded", "forward_facing"):
    other = capacity.derive_capacity(dataclasses.replace(scene, kind=kind, background_color=None))
    assert (other.pixel_samples, other.sh_degree, other.coarse_to_fine) == (
        1, capacity.SH_DEGREE, 0.0)
  # Runs saved before the fields existed read as one ray a pixel, the full view dependence.
  saved = dataclasses.asdict(derived)
  del saved["pixel_samples"], saved["sh_degree"]
  assert capacity.Capacity.from_json(saved).pixel_samples == 1
  assert capacity.Capacity.from_json(saved).sh_degree == capacity.SH_DEGREE


def test_forward_facing_grid_resolves_one_pixel_angle_per_finest_cell():
  derived = capacity.derive_capacity(FORWARD_FACING)
  focal = LEGO_100.camera_distance / LEGO_100.pixel_footprint  # 138.9 px
  assert 1.6 * focal <= derived.finest_resolution <= 1.6 * focal + 8
  assert "NDC" in capacity.describe(derived)
  # Runs recorded before the warp existed (no perspective) keep their box.
  legacy = capacity.derive_capacity(dataclasses.replace(FORWARD_FACING, perspective=None))
  assert not legacy.perspective_warp


@pytest.mark.parametrize("yaw_degrees", [0.0, 90.0, 150.0])
def test_perspective_warp_spans_the_cameras_field_of_view_in_any_orientation(yaw_degrees):
  from signerf_jax import camera as camera_lib  # pylint: disable=g-import-not-at-top

  yaw = np.radians(yaw_degrees)
  rotation = np.array([[np.cos(yaw), 0.0, np.sin(yaw)], [0.0, 1.0, 0.0],
                       [-np.sin(yaw), 0.0, np.cos(yaw)]])
  position = np.array([0.3, -0.2, 0.5])
  pose = np.concatenate([rotation, position[:, None]], axis=1)[None]
  cameras = camera_lib.Cameras.create(pose, 50.0, width=100, height=60)
  warp = PerspectiveWarp.from_cameras(cameras, near=0.5, far=4.0)
  np.testing.assert_allclose(warp.centre, position, atol=1e-6)
  np.testing.assert_allclose(warp.low[:2], (-1.0, -0.6), rtol=1e-5)  # half sizes / focal
  np.testing.assert_allclose(warp.high[:2], (1.0, 0.6), rtol=1e-5)
  # Disparity from the far centre ray's depth to the near corner ray's (depth = distance * cos).
  corner_cos = 1.0 / np.sqrt(1.0 + 1.0**2 + 0.6**2)
  np.testing.assert_allclose((warp.low[2], warp.high[2]), (1 / 4.0, 1 / (0.5 * corner_cos)),
                             rtol=1e-5)
  # What the camera sees between near and far lands inside the unit cube; the optical axis
  # through its centre.
  seen = np.array([[0.0, 0.0, -0.5], [0.3, -0.1, -2.0], [-3.9, 0.0, -3.95]])
  coordinates = np.asarray(warp(seen @ rotation.T + position))
  assert np.all((coordinates >= 0) & (coordinates <= 1)), coordinates
  np.testing.assert_allclose(coordinates[:2, :2].mean(), 0.5, atol=0.1)
  np.testing.assert_allclose(warp.inverse(coordinates), seen @ rotation.T + position, atol=1e-4)
  assert PerspectiveWarp.from_json(json.loads(json.dumps(
      dataclasses.asdict(warp)))) == warp


def test_perspective_warp_of_cameras_looking_all_around_is_an_input_error():
  from signerf_jax import camera as camera_lib  # pylint: disable=g-import-not-at-top

  angles = np.linspace(0, 2 * np.pi, 8, endpoint=False)
  eyes = np.stack([np.cos(angles), np.sin(angles), np.zeros(8)], -1).astype(np.float32)
  cameras = camera_lib.Cameras.create(np.asarray(camera_lib.look_at(eyes, np.zeros(3, np.float32))),
                                      50.0, width=100, height=60)
  with pytest.raises(InputError, match="not a forward-facing capture"):
    PerspectiveWarp.from_cameras(cameras, near=0.5, far=4.0)


@pytest.mark.parametrize("bounds, problem", [
    (((0, 0, 0), (1e-300, 1e-300, 1e-300)), "degenerate"),
    (((0, 0, 0), (0, 0, 0)), "degenerate"),
    (((-1, -1, -1), (1, -2, 1)), "degenerate"),
    (((-1, -1, -1), (1, float("inf"), 1)), "finite corners"),
    (((-1, -1, float("nan")), (1, 1, 1)), "finite corners"),
], ids=["tiny", "point", "inverted", "infinite", "nan"])
def test_degenerate_or_non_finite_bounds_are_an_input_error_not_a_division(bounds, problem):
  with pytest.raises(InputError, match=problem) as error:
    capacity.derive_capacity(dataclasses.replace(LEGO_100, bounds=bounds))
  assert error.value.field == "scene_bounds"


@pytest.mark.parametrize("field", ["camera_distance", "pixel_footprint"])
def test_non_finite_camera_geometry_is_an_input_error(field):
  with pytest.raises(InputError, match="not positive and finite") as error:
    capacity.derive_capacity(dataclasses.replace(LEGO_100, **{field: float("nan")}))
  assert error.value.field == field


def test_scene_info_from_a_dataset_with_degenerate_bounds_names_the_dataset(sphere):
  degenerate = dataclasses.replace(sphere, root="/data/sphere",
                                   scene_bounds=np.full((2, 3), 0.5, np.float32))
  with pytest.raises(InputError, match="degenerate") as error:
    scene_info.SceneInfo.from_dataset(degenerate)
  assert (error.value.path, error.value.field) == ("/data/sphere", "scene_bounds")
