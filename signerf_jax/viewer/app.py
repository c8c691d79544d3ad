"""The viewer: a viser scene of the trained NeRF, its cameras and the edit's selection, and a panel
that previews and saves the edit.

The scene is drawn in the NeRF's scene frame (where it renders and where its cameras are); the
panel's numbers are the dataset's own units, as every command's. What the viewer does goes
through the command line's functions: `nerf.render` (frames), `editing.place` (moving the
selection, standing it on the surface), `editing.stages.reference` (the reference cameras),
`editing.commands` (the preview and the saved config.gin).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import re
import sys
import threading
from pathlib import Path

import numpy as np
import viser
from viser import transforms

from signerf_jax import configs, files, ownership
from signerf_jax.data import frame as frame_lib
from signerf_jax.editing import place
from signerf_jax.editing.commands import gin_value, parse_edit_config, run_command
from signerf_jax.editing.commands.place import selection_bindings
from signerf_jax.editing.generation import SheetRecipe
from signerf_jax.editing.stages import reference as reference_stage
from signerf_jax.editing.stages import sheets as sheets_stage
from signerf_jax.errors import InputError
from signerf_jax.geometry import reference_cameras
from signerf_jax.geometry import selection as selection_lib
from signerf_jax.viewer import access, edit_session, progressive
from signerf_jax.viewer.cameras import ViewPose, pose_of_camera

# The sheet dropdown's entry for EditConfig.sheet = "" (the sheet of the edit's seed).
SEED_SHEET = "(seed)"
SELECTION_COLOR = (230, 40, 40)
DATASET_CAMERA_COLOR = (60, 60, 60)
REFERENCE_CAMERA_COLOR = (30, 110, 230)
LINE_PIXELS = 1.5
CONTROLNET_SCALE = "first_iteration/GenerationOptions.controlnet_conditioning_scale"
def box_edges(lower, upper) -> np.ndarray:
  """[12, 2, 3] the edges of the axis-aligned box [lower, upper]."""
  corners = np.asarray(selection_lib.Box.create(lower, upper).corners)
  pairs = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
  return np.asarray([[corners[a], corners[b]] for a, b in pairs], np.float32)


class Viewer:
  """`signerf view`'s server: one per run (and edit directory)."""

  def __init__(self, run_dir: str | Path, edit_dir: str | Path, *, proxy: str = "primitive:box",
               host: str = "127.0.0.1", port: int = 8080,
               heights: tuple[int, ...] = progressive.HEIGHTS):
    self.run_dir, self.edit_dir = Path(run_dir), Path(edit_dir)
    self.heights = heights
    self.context, saved_selection, prompt = edit_session.load(self.run_dir, self.edit_dir, proxy)
    self.dataset = self.context.dataset
    self.nerf = self.context.nerf(0)
    self.selection = saved_selection or edit_session.default_selection(self.dataset, proxy)
    self._lock = threading.RLock()  # The selection and the scene nodes that show it.
    self._worker = concurrent.futures.ThreadPoolExecutor(1, "signerf-view-work")  # gin, stages
    self._renderers: dict[int, progressive.ProgressiveRenderer] = {}
    self.shown_frames: dict[int, progressive.Frame] = {}  # The last frame sent to each client.
    # What is drawn is sized by how far the cameras stand from the scene's centre (the bounds of
    # an unbounded scene say nothing of the size of what the cameras see).
    centre = np.mean(np.asarray(self.dataset.scene_bounds, np.float64), axis=0)
    self._distance = float(np.median(np.linalg.norm(
        np.asarray(self.dataset.cameras.positions, np.float64) - centre, axis=1)))
    self.handle = None
    self._view_looked_through: int | None = None
    # The page and its websocket ask for this token (printed in `url`): any other page the
    # user has open could otherwise drive the viewer (access.py).
    self.host, self.token = host, access.new_token()
    self.server = access.serve(host, port, self.token)
    self.server.scene.set_up_direction(tuple(reference_cameras.scene_up(
        self.dataset.cameras)))
    self._draw_scene()
    self._build_panel(prompt)
    self.show_selection()
    self.server.on_client_connect(self._connect)
    self.server.on_client_disconnect(self._disconnect)

  @property
  def url(self) -> str:
    """The page's address, with its token (http://127.0.0.1:8080/?token=...)."""
    return access.browser_url(self.host, self.server.get_port(), self.token)

  def close(self) -> None:
    for renderer in list(self._renderers.values()):
      renderer.close()
    self._worker.shutdown(wait=True)
    self.server.stop()

  # The scene ---------------------------------------------------------------------------------

  def _draw_scene(self) -> None:
    scene, cameras = self.server.scene, self.dataset.cameras
    scene.add_frame("/scene_frame", axes_length=0.05 * self._distance,
                    axes_radius=0.002 * self._distance)
    scene.add_line_segments("/scene_bounds", box_edges(*self.dataset.scene_bounds),
                            (120, 120, 120),
                            thickness=LINE_PIXELS, thickness_units="screen")
    self.camera_frustums = []
    for index in range(cameras.num_cameras):
      pose = pose_of_camera(cameras, index)
      # Without the photo on the frustum: looking through a camera, its photo would cover the
      # NeRF (the panel shows it instead).
      frustum = scene.add_camera_frustum(
          f"/dataset_cameras/{index}", fov=pose.vertical_fov, aspect=pose.aspect,
          scale=0.03 * self._distance, thickness=LINE_PIXELS, thickness_units="screen",
          color=DATASET_CAMERA_COLOR, wxyz=pose.wxyz, position=pose.position)
      frustum.on_click(lambda event, index=index: self.jump_to_view(event.client, index))
      self.camera_frustums.append(frustum)

  def show_selection(self) -> None:
    """Draws the selection (its mesh under its handle), its handle and the reference cameras."""
    with self._lock:
      rotation, position = place.handle_pose(self.selection, self.dataset)
      mesh = place.selection_mesh(self.selection, self.dataset)
      local = (np.asarray(mesh.vertices, np.float64) - position) @ rotation
      wxyz = transforms.SO3.from_matrix(rotation).wxyz
      if self.handle is None:
        self.handle = self.server.scene.add_transform_controls(
            "/selection", scale=0.6 * float(np.ptp(np.asarray(mesh.vertices), 0).max()),
            depth_test=False,
            disable_rotations=self.selection.kind == "box", wxyz=wxyz, position=position)
        self.handle.on_update(self.handle_moved)
      else:
        self.handle.wxyz, self.handle.position = wxyz, position
      self.selection_mesh = self.server.scene.add_mesh_simple(
          "/selection/mesh", local.astype(np.float32), np.asarray(mesh.faces, np.int32),
          color=SELECTION_COLOR, opacity=0.6)
      self._selection_points = np.asarray(mesh.vertices, np.float64)
      self._show_reference_cameras()
      self._show_selection_fields()

  def _show_reference_cameras(self) -> None:
    try:
      cameras, _ = reference_stage.first_iteration_cameras(self.context, self._selection_points)
    except InputError as error:
      self._say(f"reference cameras: {error}")
      return
    for index in range(cameras.num_cameras):
      pose = pose_of_camera(cameras, index)
      self.server.scene.add_camera_frustum(
          f"/reference_cameras/{index}", fov=pose.vertical_fov, aspect=pose.aspect,
          scale=0.04 * self._distance, thickness=2 * LINE_PIXELS, thickness_units="screen",
          color=REFERENCE_CAMERA_COLOR, wxyz=pose.wxyz, position=pose.position,
          visible=self.show_reference.value)

  def handle_moved(self, event) -> None:
    if event.phase != "end":  # The mesh follows its handle in the browser meanwhile.
      return
    with self._lock:
      rotation = transforms.SO3(np.asarray(self.handle.wxyz)).as_matrix()
      self.selection = place.moved_selection(self.selection, self.dataset, rotation,
                                             np.asarray(self.handle.position))
      self.show_selection()

  # The browser's view ------------------------------------------------------------------------

  def _connect(self, client: viser.ClientHandle) -> None:
    def show(frame: progressive.Frame) -> None:
      client.scene.set_background_image(frame.rgb, format="jpeg", jpeg_quality=90,
                                        depth=frame.depth)
      self.shown_frames[client.client_id] = frame

    def frames(pose, is_current):
      return progressive.render_progressively(self.nerf.model, self.nerf.variables, pose,
                                              is_current, heights=self.heights)

    self._renderers[client.client_id] = progressive.ProgressiveRenderer(frames, show)
    client.camera.on_update(lambda _: self.render_view(client))
    self.jump_to_view(client, 0)

  def render_view(self, client: viser.ClientHandle) -> None:
    """Renders what the browser's camera sees. The browser reports the moves its user makes;
    after the viewer moves the camera itself, it asks here."""
    camera = client.camera
    self._renderers[client.client_id].request(ViewPose(
        tuple(camera.wxyz), tuple(camera.position), camera.fov, camera.aspect))

  def _disconnect(self, client: viser.ClientHandle) -> None:
    renderer = self._renderers.pop(client.client_id, None)
    if renderer is not None:
      renderer.close()

  def jump_to_view(self, client: viser.ClientHandle, index: int) -> None:
    """Puts the browser's camera at dataset view `index` and shows that view's image."""
    pose = pose_of_camera(self.dataset.cameras, index)
    with client.atomic():
      client.camera.fov = pose.vertical_fov
      client.camera.position = pose.position
      client.camera.wxyz = pose.wxyz
    self.render_view(client)
    # Its own frustum would frame the view from inside: hidden while looking through it.
    if self._view_looked_through is not None:
      self.camera_frustums[self._view_looked_through].visible = True
    self.camera_frustums[index].visible, self._view_looked_through = False, index
    self.view_image.image = np.asarray(self.dataset.images[index], np.float32)
    self.view_image.label = f"view {index}: {self.dataset.image_names[index]}"

  # The panel ---------------------------------------------------------------------------------

  def _build_panel(self, prompt: str) -> None:
    gui, settings = self.server.gui, self.context.settings
    frame = self.dataset.frame
    gui.add_markdown(f"**signerf view** `{self.run_dir}`  \n"
                     + (frame_lib.summary_line(frame) if frame else "scene frame: not recorded")
                     + "  \nNumbers below are in the dataset's own units.")
    with gui.add_folder("Selection"):
      self.selection_kind = gui.add_markdown("")
      self.position_field = gui.add_vector3("Position", (0.0, 0.0, 0.0), step=1e-3)
      self.size_field = gui.add_vector3("Box size", (1.0, 1.0, 1.0), min=(1e-6,) * 3,
                                        step=1e-3)
      self.proxy_size_field = gui.add_number("Proxy size", 1.0, min=1e-6, step=1e-3)
      self.heading_field = gui.add_number("Heading (degrees)", 0.0, step=1.0)
      snap = gui.add_button("Stand on surface")
      self.show_reference = gui.add_checkbox("Reference cameras", True)
    for field in (self.position_field, self.size_field, self.proxy_size_field,
                  self.heading_field):
      field.on_update(self._fields_changed)
    snap.on_click(lambda _: self.stand_on_surface())
    self.show_reference.on_update(lambda _: self._show_reference_cameras())
    with gui.add_folder("Edit"):
      self.prompt_field = gui.add_text("Prompt", prompt)
      self.seed_field = gui.add_number("Seed", settings.edit.seed, min=0, step=1)
      self.controlnet_field = gui.add_slider(
          "ControlNet scale", min=0.0, max=2.0, step=0.05,
          initial_value=settings.generation[0].controlnet_conditioning_scale)
      self.preview_button = gui.add_button("Preview")
      self.progress = gui.add_progress_bar(0.0, visible=False)
      self.status = gui.add_markdown(f"Edit directory: `{self.edit_dir}`")
      self.sheet_field = gui.add_dropdown("Sheet", [settings.edit.sheet or SEED_SHEET])
      self.reroll_tiles = gui.add_text("Re-roll tiles", "")
      self.reroll_seed = gui.add_number("Re-roll seed", 1, min=0, step=1)
      reroll = gui.add_button("Re-roll")
      save = gui.add_button("Save")
      self.candidates: list = []
    self.recipes = tuple(settings.preview.recipes)
    self.preview_button.on_click(lambda _: self.submit(self.preview))
    reroll.on_click(lambda _: self.submit(self.reroll))
    save.on_click(lambda _: self.submit(self.save))
    with gui.add_folder("Dataset view"):
      self.view_image = gui.add_image(np.zeros((8, 8, 3), np.float32), label="view")

  def _show_selection_fields(self) -> None:
    """The panel's selection fields from `self.selection` (dataset units)."""
    selection, box = self.selection, self.selection.kind == "box"
    self.selection_kind.content = (
        "Box selection: drag the handle to move it" if box else
        f"Proxy `{selection.proxy}`: drag the handle to move and turn it")
    if box:
      lower, upper = np.asarray(selection.box_min), np.asarray(selection.box_max)
      self.position_field.value = tuple(map(float, (lower + upper) / 2))
      self.size_field.value = tuple(map(float, upper - lower))
    else:
      self.position_field.value = tuple(map(float, selection.ground_position))
      self.proxy_size_field.value = float(selection.ground_size)
      self.heading_field.value = float(selection.heading_degrees)
    self.size_field.visible = box
    self.proxy_size_field.visible = self.heading_field.visible = not box

  def _fields_changed(self, event) -> None:
    if event.client is None:  # Set by the viewer itself.
      return
    with self._lock:
      position = np.asarray(self.position_field.value, np.float64)
      if self.selection.kind == "box":
        half = np.asarray(self.size_field.value, np.float64) / 2
        changes = dict(box_min=tuple(map(float, position - half)),
                       box_max=tuple(map(float, position + half)))
      else:
        changes = dict(ground_position=tuple(map(float, position)),
                       ground_size=float(self.proxy_size_field.value),
                       heading_degrees=float(self.heading_field.value))
      self.selection = dataclasses.replace(self.selection, **changes)
      self.show_selection()

  def stand_on_surface(self) -> None:
    with self._lock:
      try:
        self.selection = place.stand_on_surface(self.nerf.model, self.nerf.variables,
                                                self.dataset, self.selection)
      except InputError as error:
        self._say(f"Stand on surface: {error}")
        return
      self.show_selection()
      self._say("Stood on the surface under the proxy's ground point.")

  # Work: preview, re-roll, save (one at a time, off the server's threads) ----------------------

  def _say(self, text: str) -> None:
    self.status.content = text
    print(f"signerf view: {text}", file=sys.stderr, flush=True)

  def submit(self, work) -> concurrent.futures.Future:
    def guarded():
      try:
        return work()
      except InputError as error:
        self._say(f"error: {error}")
      finally:
        self.progress.visible = False
        self.preview_button.disabled = False
    return self._worker.submit(guarded)

  def bindings(self) -> list[str]:
    """The panel's settings as gin bindings: the selection, prompt, seed, ControlNet scale, the
    chosen sheet and the re-rolled candidates."""
    with self._lock:
      bindings = selection_bindings(self.selection)
    bindings += [f"EditConfig.original_run = {gin_value(str(self.run_dir.resolve()))}",
                 f"EditConfig.prompt = {gin_value(self.prompt_field.value)}",
                 f"EditConfig.seed = {int(self.seed_field.value)}",
                 f"{CONTROLNET_SCALE} = {float(self.controlnet_field.value)}",
                 f"PreviewConfig.recipes = {gin_value(self.recipes)}"]
    if self.sheet_field.value != SEED_SHEET:
      bindings.append(f"EditConfig.sheet = {gin_value(self.sheet_field.value)}")
    return bindings

  def save(self) -> Path:
    parse_edit_config(self.edit_dir, (), self.bindings())
    with ownership.claimed(self.edit_dir, ownership.EDIT,
                           inputs=(("run", self.run_dir), ("data", self.dataset.root))):
      path = configs.save_gin_config(self.edit_dir)
    self._say(f"Saved to `{path}`: `signerf edit --edit {self.edit_dir}` continues from here.")
    return path

  def preview(self) -> list[Path]:
    self.preview_button.disabled = True
    self.progress.value, self.progress.visible = 0.0, True
    parse_edit_config(self.edit_dir, (), self.bindings())

    def log(line: str) -> None:
      stage = re.match(r"\[(\d+)/(\d+)\]", line)
      if stage:
        self.progress.value = 100.0 * (int(stage[1]) - 1) / int(stage[2])
      self._say(line)

    context = run_command("preview", self.edit_dir, progress=False, log=log)
    recipes = sheets_stage.preview_recipes(context)
    paths = [sheets_stage.candidate_path(context, recipe).with_suffix(".png")
             for recipe in recipes]
    for image in self.candidates:
      image.remove()
    with self.server.gui.add_folder("Candidate sheets"):
      self.candidates = [self.server.gui.add_image(files.read_image(path),
                                                   label=f"sheet {recipe}")
                         for recipe, path in zip(recipes, paths)]
    chosen = self.sheet_field.value
    self.sheet_field.options = [str(recipe) for recipe in recipes]
    self.sheet_field.value = chosen if chosen in self.sheet_field.options else str(recipes[0])
    self._say(f"{len(recipes)} candidate sheets: pick one (Sheet), re-roll tiles or save.")
    return paths

  def reroll(self) -> list[Path]:
    tiles = self.reroll_tiles.value.replace(" ", "")
    sheet = self.sheet_field.value
    sheet = str(int(self.seed_field.value)) if sheet == SEED_SHEET else sheet
    recipe = f"{sheet}/{tiles}@{int(self.reroll_seed.value)}"
    SheetRecipe.parse(recipe)  # A bad tile list is an error here, not deep in the preview.
    self.recipes = tuple(dict.fromkeys(self.recipes + (recipe,)))
    return self.preview()
