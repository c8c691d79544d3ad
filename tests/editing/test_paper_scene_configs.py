"""The paper's scene configs (gin_configs/paper_scenes.gin + paper_scenes/*.gin): every scene
parses, binds only existing configurables, holds its row of the paper's table, and refuses to
run until the user's inputs (dataset, model, selection) are given, naming the missing binding."""

import gin
import pytest

from signerf_jax import configs
from signerf_jax.editing import commands
from signerf_jax.errors import InputError

# The paper's appendix table "Scene List", transcribed independently of the gin files:
# scene -> (kind, (strength, ControlNet scale) of the first iteration, of the second or None,
# guidance). field_cow ran on SD 1.5 "without a denoising strength": the full schedule.
PAPER_TABLE = {
    "person_sport": ("box", (0.9, 0.4), None, 7.0),
    "person_pirate": ("box", (0.95, 0.4), (0.5, 0.8), 7.5),
    "person_batman": ("box", (0.95, 0.4), (0.5, 1.0), 6.0),
    "plushy_ironman": ("box", (0.9, 1.0), None, 7.0),
    "plushy_tiger": ("box", (0.6, 1.0), None, 7.0),
    "plushy_gold": ("box", (0.95, 1.0), None, 7.0),
    "bear_grizzly": ("box", (0.9, 0.95), None, 7.0),
    "bear_polar": ("box", (0.9, 0.95), None, 7.0),
    "bear_panda": ("box", (0.9, 0.95), None, 7.0),
    "bear_rabbit": ("proxy", (0.95, 1.0), None, 7.0),
    "field_cow": ("proxy", (1.0, 0.7), None, 7.5),
    "urban_house": ("proxy", (1.0, 0.8), None, 7.0),
}
COMMON_INPUTS = {"EditConfig.data": "'/data/scene'", "EditConfig.model": "'/models/sdxl'"}
SELECTION_INPUTS = {
    "box": {"SelectionConfig.box_min": "(-0.2, -0.2, 0.0)",
            "SelectionConfig.box_max": "(0.2, 0.2, 0.5)"},
    "proxy": {"SelectionConfig.proxy": "'primitive:cow'",
              "SelectionConfig.ground_position": "(0.0, 0.0, 0.0)",
              "SelectionConfig.ground_size": "0.5"},
}


def user_inputs(scene: str) -> dict[str, str]:
  return {**COMMON_INPUTS, **SELECTION_INPUTS[PAPER_TABLE[scene][0]]}


def parse_scene(script, scene: str, inputs: dict[str, str]) -> None:
  configs.parse_gin(script.scene_gin_files(scene),
                    [f"{name} = {value}" for name, value in inputs.items()])


@pytest.fixture(scope="module")
def script(experiment_script):
  return experiment_script("paper_scenes")


@pytest.fixture(autouse=True)
def clear_gin():
  yield
  gin.clear_config()


def test_there_is_one_config_per_row_of_the_papers_table(script):
  assert script.scene_names() == sorted(PAPER_TABLE)


@pytest.mark.parametrize("scene", sorted(PAPER_TABLE))
def test_a_scene_binds_its_row_of_the_table(script, scene):
  kind, first, second, guidance = PAPER_TABLE[scene]
  parse_scene(script, scene, user_inputs(scene))
  settings = commands.edit_settings()
  edit, selection, sheet = settings.edit, settings.selection, settings.sheet
  assert edit.prompt and edit.data == "/data/scene" and edit.model == "/models/sdxl"
  assert selection.kind == kind
  # The paper's choice: retrain for inserted objects, fine-tune for edits.
  assert edit.nerf_update == ("retrain" if kind == "proxy" else "finetune")
  assert (sheet.rows, sheet.columns) == (2, 3)
  assert edit.second_iteration == (second is not None)
  for iteration, expected in ((1, first), (2, second)):
    if expected is None:
      continue
    options = settings.generation_options(iteration)
    assert (options.strength, options.controlnet_conditioning_scale) == expected
    assert options.guidance_scale == guidance and options.paste_back
  assert settings.training["original"].steps == 30000


@pytest.mark.parametrize("scene", ["bear_grizzly", "person_batman", "field_cow"])
def test_every_missing_user_input_is_named(script, scene):
  for missing in user_inputs(scene):
    inputs = {name: value for name, value in user_inputs(scene).items() if name != missing}
    with pytest.raises(InputError, match=f"{missing} set to `%gin.REQUIRED`") as error:
      parse_scene(script, scene, inputs)
    assert "paper_scenes" in error.value.path


def test_the_script_stops_before_writing_anything_without_the_users_inputs(script, tmp_path,
                                                                          capsys):
  out, results = tmp_path / "edit", tmp_path / "results"
  code = script.main(["--scene", "bear_grizzly", "--edit", str(out),
                      "--results", str(results), "--model", str(tmp_path)])
  assert code == 2
  assert "set to `%gin.REQUIRED` but not subsequently overridden" in capsys.readouterr().err
  assert not out.exists() and not results.exists()
