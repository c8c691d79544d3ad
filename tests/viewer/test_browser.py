"""`signerf view` in a real browser: a headless Chromium (Debian's chromium and chromium-driver,
driven by selenium) opens the page the viewer serves for a tiny trained run, sees the NeRF,
the cameras and the proxy, moves the proxy through the panel and by dragging its handle with
the mouse, previews sheets and saves.

Skipped, with the reason, where no Chromium is installed (the README says how to install one;
CI installs it)."""

from __future__ import annotations

import http.server
import shutil
import threading
import time

import cv2
import numpy as np
import pytest

from signerf_jax import camera, configs
from signerf_jax.editing import place
from signerf_jax.editing.commands import edit_settings, parse_edit_config
from signerf_jax.editing.config import SelectionConfig
from signerf_jax.viewer import access, app
from signerf_jax.viewer.cameras import ViewPose, cameras_for_pose

CHROMIUM, CHROMEDRIVER = shutil.which("chromium"), shutil.which("chromedriver")
pytestmark = [pytest.mark.slow, pytest.mark.skipif(
    CHROMIUM is None or CHROMEDRIVER is None,
    reason="no headless Chromium: install Debian's chromium and chromium-driver packages "
    "(README, 'The viewer')")]
WINDOW = (1000, 700)


def wait_for(condition, seconds: float, what: str):
  deadline = time.monotonic() + seconds
  while time.monotonic() < deadline:
    value = condition()
    if value:
      return value
    time.sleep(0.1)
  raise AssertionError(f"timed out after {seconds} s waiting for {what}")


@pytest.fixture(scope="module")
def viewer(viewed_run, viewed_edit):
  run_dir, _ = viewed_run
  served = app.Viewer(run_dir, viewed_edit, port=8093, heights=(32, 64))
  yield served
  served.close()


@pytest.fixture(scope="module")
def browser(viewer):
  from selenium import webdriver  # pylint: disable=g-import-not-at-top
  from selenium.webdriver.chrome.service import Service  # pylint: disable=g-import-not-at-top
  options = webdriver.ChromeOptions()
  options.binary_location = CHROMIUM
  for argument in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
                   f"--window-size={WINDOW[0]},{WINDOW[1]}", "--use-angle=swiftshader",
                   "--enable-unsafe-swiftshader", "--force-device-scale-factor=1"):
    options.add_argument(argument)
  driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
  open_viewer(driver, viewer)
  yield driver
  driver.quit()


def open_viewer(driver, viewer) -> None:
  """Opens the page as its user does: the address `signerf view` prints, whose ?token= lets the
  page in and sets the cookie its websocket carries (the page drops the query string)."""
  assert "?token=" in viewer.url
  driver.get(viewer.url)


def screenshot(browser) -> np.ndarray:
  """[H, W, 3] uint8 RGB of the page."""
  image = cv2.imdecode(np.frombuffer(browser.get_screenshot_as_png(), np.uint8),
                       cv2.IMREAD_COLOR)
  return image[..., ::-1]


def client_of(viewer):
  return wait_for(lambda: next(iter(viewer.server.get_clients().values()), None), 60,
                  "the page to connect")


def browser_pose(client) -> ViewPose:
  camera_handle = client.camera
  return ViewPose(tuple(camera_handle.wxyz), tuple(camera_handle.position), camera_handle.fov,
                  camera_handle.aspect)


def project(pose: ViewPose, points, size) -> np.ndarray:
  """[K, 2] pixel coordinates of scene points in a `size` (width, height) canvas."""
  cameras = cameras_for_pose(pose, size[1])
  pixels, _ = camera.project(cameras, np.asarray(points, np.float32))
  return np.asarray(pixels[0]) * (size[0] / cameras.width, 1.0)


def canvas_of(browser) -> tuple[int, int, int, int]:
  from selenium.webdriver.common.by import By  # pylint: disable=g-import-not-at-top
  canvas = max(browser.find_elements(By.TAG_NAME, "canvas"),
               key=lambda element: element.size["width"] * element.size["height"])
  return (canvas.location["x"], canvas.location["y"], canvas.size["width"],
          canvas.size["height"])


def field_inputs(browser, label: str):
  """The <input> elements of the panel field labelled `label`."""
  from selenium.webdriver.common.by import By  # pylint: disable=g-import-not-at-top
  labels = [element for element in browser.find_elements(
      By.XPATH, f"//*[normalize-space(text())='{label}']") if element.is_displayed()]
  assert labels, f"no panel field labelled {label!r}"
  row = labels[0].find_element(By.XPATH, "./ancestor::*[.//input][1]")
  return row.find_elements(By.TAG_NAME, "input")


def button(browser, text: str):
  from selenium.webdriver.common.by import By  # pylint: disable=g-import-not-at-top
  return wait_for(lambda: next((element for element in browser.find_elements(
      By.XPATH, f"//button[normalize-space(.)='{text}']") if element.is_displayed()), None),
      30, f"the {text!r} button")


def canvas_screenshot(browser, canvas) -> np.ndarray:
  """[H, W, 3] float32 in [0, 1]: the page's 3D canvas."""
  left, top, width, height = canvas
  time.sleep(1.0)  # The browser draws what it received.
  return screenshot(browser)[top:top + height, left:left + width].astype(np.float32) / 255


def changed_where_hidden(browser, canvas, nodes) -> np.ndarray:
  """[H, W] bool: where the canvas changes when the scene `nodes` are hidden."""
  shown = canvas_screenshot(browser, canvas)
  for node in nodes:
    node.visible = False
  hidden = canvas_screenshot(browser, canvas)
  for node in nodes:
    node.visible = True
  return np.abs(shown - hidden).max(-1) > 0.1


def test_the_page_shows_the_nerf_the_cameras_and_the_proxy(viewer, browser):
  client = client_of(viewer)
  frame = wait_for(lambda: (shown := viewer.shown_frames.get(client.client_id)) is not None
                   and shown.height == 64 and shown, 120, "the finest frame")
  canvas = canvas_of(browser)
  width, height = canvas[2:]
  page = canvas_screenshot(browser, canvas)
  # The NeRF's frame is the page's background: where nothing is drawn over it, the page shows
  # the frame's pixels (resized to the canvas; JPEG-coded).
  expected = cv2.resize(frame.rgb, (width, height), interpolation=cv2.INTER_LINEAR)
  difference = np.abs(page - expected).max(-1)
  assert np.median(difference) < 0.06, np.median(difference)
  # The proxy: hiding it changes the page where it stands, and only there.
  mesh = place.selection_mesh(viewer.selection, viewer.dataset)
  corners = project(browser_pose(client), np.asarray(mesh.vertices), (width, height))
  (x0, y0), (x1, y1) = corners.min(0) - 4, corners.max(0) + 4
  changed = changed_where_hidden(browser, canvas, [viewer.selection_mesh])
  inside = np.zeros_like(changed)
  inside[max(int(y0), 0):int(y1) + 1, max(int(x0), 0):int(x1) + 1] = True
  assert changed.sum() > 100 and changed[inside].sum() > 0.95 * changed.sum(), (
      changed.sum(), changed[inside].sum())
  # The dataset cameras, seen from above and behind them: hiding their frustums changes the page
  # (their lines).
  reach = np.linalg.norm(np.asarray(viewer.dataset.cameras.positions), axis=1).max()
  client.camera.position = 2.0 * reach * np.array([0.6, -0.6, 0.5])
  client.camera.look_at = np.zeros(3)
  viewer.shown_frames.pop(client.client_id)
  viewer.render_view(client)
  wait_for(lambda: (shown := viewer.shown_frames.get(client.client_id)) is not None
           and shown.height == 64, 120, "the finest frame from above")
  assert changed_where_hidden(browser, canvas, viewer.camera_frustums).sum() > 100


def test_moving_the_proxy_in_the_panel_previewing_and_saving(viewer, browser, viewed_edit):
  from selenium.webdriver.common.keys import Keys  # pylint: disable=g-import-not-at-top
  client_of(viewer)
  before = viewer.selection
  moved_x = round(before.ground_position[0] + 0.05, 3)  # The field shows 3 decimals.
  # Typed as a user does; a keystroke can be lost while the panel redraws, so up to 3 tries.
  for attempt in range(3):
    inputs = field_inputs(browser, "Position")
    assert len(inputs) == 3
    inputs[0].click()
    inputs[0].send_keys(Keys.CONTROL, "a", Keys.BACKSPACE)
    # The field drops a minus typed into an empty field: the digits first, then the sign.
    inputs[0].send_keys(str(abs(moved_x)), Keys.HOME, "-" if moved_x < 0 else "", Keys.ENTER)
    try:
      wait_for(lambda: viewer.selection.ground_position[0] == pytest.approx(moved_x, abs=1e-6),
               10, "the proxy to move")
      break
    except AssertionError:
      if attempt == 2:
        raise
  assert viewer.selection.ground_position[1:] == before.ground_position[1:]
  # Its handle moves with it, to where the edit will put it (the viewer's thread sets the
  # selection first and the handle after it: waited for, not read at once).
  _, handle_position = place.handle_pose(viewer.selection, viewer.dataset)
  wait_for(lambda: np.allclose(viewer.handle.position, handle_position, atol=1e-5), 10,
           "the handle to follow the proxy")

  button(browser, "Preview").click()
  from selenium.webdriver.common.by import By  # pylint: disable=g-import-not-at-top
  wait_for(lambda: len([image for image in browser.find_elements(By.TAG_NAME, "img")
                        if image.is_displayed() and image.size["width"] > 20]) >= 3,
           600, "the candidate sheets (and the dataset view) to appear")
  assert (viewed_edit / "preview" / "candidates" / "0.png").is_file()
  assert viewer.sheet_field.options == ("0", "1")

  button(browser, "Save").click()
  wait_for(lambda: "Saved" in viewer.status.content, 30, "the save")
  parse_edit_config(viewed_edit, (), ())
  saved = configs.build(SelectionConfig)
  assert saved.ground_position[0] == pytest.approx(moved_x, abs=1e-6)
  assert edit_settings().edit.prompt == "a red cow"


def test_dragging_the_handle_with_the_mouse_moves_the_proxy_along_the_arrow(viewer, browser):
  from selenium.webdriver.common import action_chains  # pylint: disable=g-import-not-at-top
  from selenium.webdriver.common.by import By  # pylint: disable=g-import-not-at-top
  client = client_of(viewer)
  viewer.jump_to_view(client, 0)
  time.sleep(1.0)
  width, height = canvas_of(browser)[2:]
  pose = browser_pose(client)
  rotation, position = place.handle_pose(viewer.selection, viewer.dataset)
  # The handle's arrow that looks longest from here, grabbed near its tip.
  arrows = 0.8 * viewer.handle.scale * rotation.T  # [3 axes, 3]
  ends = [project(pose, np.stack([position, position + arrow]), (width, height))
          for arrow in arrows]
  axis = int(np.argmax([np.linalg.norm(end[1] - end[0]) for end in ends]))
  start, tip = ends[axis]
  along = (tip - start) / np.linalg.norm(tip - start)
  canvas = max(browser.find_elements(By.TAG_NAME, "canvas"),
               key=lambda element: element.size["width"] * element.size["height"])
  before = viewer.selection
  (action_chains.ActionChains(browser)
   .move_to_element_with_offset(canvas, int(tip[0] - width / 2), int(tip[1] - height / 2))
   .click_and_hold().move_by_offset(*(10 * along).round().astype(int))
   .move_by_offset(*(30 * along).round().astype(int)).release().perform())
  wait_for(lambda: viewer.selection != before, 30, "the proxy to move")
  _, moved = place.handle_pose(viewer.selection, viewer.dataset)
  shift = moved - position
  # Along the grabbed arrow, forwards, and nowhere else.
  assert np.dot(shift, rotation[:, axis]) > 0.9 * np.linalg.norm(shift) > 0
  assert viewer.selection.heading_degrees == pytest.approx(before.heading_degrees, abs=1e-3)


# Opens a websocket from the page the browser shows; reports whether it opened.
TRY_WEBSOCKET = """
const done = arguments[arguments.length - 1];
const socket = new WebSocket(arguments[0], [arguments[1]]);
socket.onopen = () => { socket.close(); done("open"); };
socket.onerror = () => done("refused");
"""


def try_websocket(browser, viewer) -> str:
  import viser  # pylint: disable=g-import-not-at-top
  browser.set_script_timeout(30)
  return browser.execute_async_script(
      TRY_WEBSOCKET, f"ws://127.0.0.1:{viewer.server.get_port()}/",
      f"viser-v{viser.__version__}")


def test_another_page_in_the_browser_cannot_drive_the_viewer(viewer, browser, tmp_path):
  """Issue 68's attack: a page of another site open in the user's browser opens a websocket to
  the viewer. Here that site is another port of 127.0.0.1, so the browser even sends the
  viewer's token cookie (cookies ignore ports): its Origin alone refuses it."""
  cookie = next(cookie for cookie in browser.get_cookies()
                if cookie["name"] == access.cookie_name(viewer.server.get_port()))
  assert cookie["value"] == viewer.token and cookie["httpOnly"]
  assert cookie["sameSite"] == "Strict"
  assert try_websocket(browser, viewer) == "open"  # From the viewer's own page.
  (tmp_path / "index.html").write_text("<html><body>another site</body></html>")
  handler = lambda *args: http.server.SimpleHTTPRequestHandler(*args, directory=tmp_path)
  other_site = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
  threading.Thread(target=other_site.serve_forever, daemon=True).start()
  try:
    browser.get(f"http://127.0.0.1:{other_site.server_address[1]}/")
    assert try_websocket(browser, viewer) == "refused"
    # Without the cookie and the token, the viewer's page itself is refused.
    browser.delete_all_cookies()
    browser.get(viewer.url.split("?")[0])
    assert "refused: no token" in browser.page_source
  finally:
    other_site.shutdown()
    other_site.server_close()
    open_viewer(browser, viewer)  # As the other tests expect the browser.
