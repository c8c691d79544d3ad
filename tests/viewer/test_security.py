"""Who may drive `signerf view`: a websocket from another site's page, or without the token the
command prints, is refused; the viewer's own page with its token is served and connects.

Every connection goes to 127.0.0.1 and gives up after seconds."""

from __future__ import annotations

import re
import socket
import urllib.error
import urllib.request

import pytest
import viser
from websockets.datastructures import Headers
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from signerf_jax import cli
from signerf_jax.viewer import access, app, command

SECONDS = 10.0


@pytest.fixture(scope="module")
def viewer(viewed_run, viewed_edit):
  served = app.Viewer(viewed_run[0], viewed_edit, port=8096, heights=(16,))
  yield served
  served.close()


def own_origin(viewer, name: str = "127.0.0.1") -> str:
  return f"http://{name}:{viewer.server.get_port()}"


def open_websocket(viewer, origin: str | None, query: str = "", cookie: str | None = None,
                   host_name: str = "127.0.0.1") -> bytes:
  """The first message the viewer sends on a websocket opened as a page does (viser's
  subprotocol) from `origin`; `host_name` is the name the request is addressed to (its Host
  header), the connection always goes to 127.0.0.1. Raises InvalidStatus when refused."""
  port = viewer.server.get_port()
  sock = socket.create_connection(("127.0.0.1", port), timeout=SECONDS)
  with connect(f"ws://{host_name}:{port}/{query}", sock=sock, origin=origin,
               additional_headers={"Cookie": cookie} if cookie else None,
               subprotocols=[f"viser-v{viser.__version__}"], open_timeout=SECONDS,
               close_timeout=SECONDS) as websocket:
    return websocket.recv(timeout=SECONDS)


def refusal(viewer, *args, **kwargs) -> str:
  """The viewer's answer to a websocket it must refuse: 403 and why."""
  with pytest.raises(InvalidStatus) as refused:
    open_websocket(viewer, *args, **kwargs)
  assert refused.value.response.status_code == 403
  return refused.value.response.body.decode()


def token_cookie(viewer, token: str | None = None) -> str:
  return f"{access.cookie_name(viewer.server.get_port())}={token or viewer.token}"


def get(url: str):
  """(status, headers, body) of an HTTP GET."""
  try:
    with urllib.request.urlopen(url, timeout=SECONDS) as response:
      return response.status, response.headers, response.read()
  except urllib.error.HTTPError as error:
    return error.code, error.headers, error.read()


@pytest.mark.slow
def test_a_websocket_from_another_sites_page_is_refused(viewer):
  # Even with the token (which another site's page cannot know): the page is not the viewer's.
  for origin in ("http://evil.example", f"http://evil.example:{viewer.server.get_port()}",
                 "http://127.0.0.1:1", "null"):
    assert "is not the viewer's own page" in refusal(viewer, origin, f"?token={viewer.token}")
  assert "Origin" in refusal(viewer, None, f"?token={viewer.token}")
  # A site whose name resolves to 127.0.0.1 (DNS rebinding) is its own origin, but not this
  # machine's name.
  rebound = f"http://evil.example:{viewer.server.get_port()}"
  assert "Host" in refusal(viewer, rebound, f"?token={viewer.token}", host_name="evil.example")


@pytest.mark.slow
def test_a_websocket_without_the_token_is_refused(viewer):
  assert "no token" in refusal(viewer, own_origin(viewer))
  assert "wrong token" in refusal(viewer, own_origin(viewer), "?token=guessed")
  assert "wrong token" in refusal(viewer, own_origin(viewer),
                                  cookie=token_cookie(viewer, "guessed"))
  # Another viewer's cookie (another port on the same machine) is not this one's.
  other = f"{access.cookie_name(viewer.server.get_port() + 1)}={viewer.token}"
  assert "no token" in refusal(viewer, own_origin(viewer), cookie=other)


@pytest.mark.slow
def test_the_viewers_own_page_with_its_token_connects(viewer):
  # As the page does: its cookie (the page opens the websocket without the query string) ...
  assert open_websocket(viewer, own_origin(viewer), cookie=token_cookie(viewer))
  # ... or the token in the query; and from localhost, the same machine as 127.0.0.1.
  assert open_websocket(viewer, own_origin(viewer), f"?token={viewer.token}")
  assert open_websocket(viewer, own_origin(viewer, "localhost"), cookie=token_cookie(viewer))


@pytest.mark.slow
def test_the_page_asks_for_the_token_and_sets_its_cookie(viewer):
  page = f"{own_origin(viewer)}/"
  status, _, body = get(page)
  assert status == 403 and b"token" in body
  assert get(f"{page}?token=guessed")[0] == 403
  status, headers, body = get(viewer.url)
  assert status == 200 and b"<html" in body.lower()[:1000]
  cookie = headers["Set-Cookie"]
  assert cookie.startswith(token_cookie(viewer) + ";")
  assert "HttpOnly" in cookie and "SameSite=Strict" in cookie


@pytest.mark.slow
def test_the_printed_address_carries_the_token(viewed_run, viewed_edit, monkeypatch, capsys):
  seen = {}

  def open_the_printed_address():
    # While `signerf view` serves: the address it printed opens the page, without its token not.
    printed = capsys.readouterr().err
    seen["url"] = re.search(r"open (http://\S+)", printed)[1]
    seen["with"] = get(seen["url"])[0]
    seen["without"] = get(seen["url"].split("?")[0])[0]
    raise KeyboardInterrupt  # Ctrl-C.

  monkeypatch.setattr(command, "wait_for_interrupt", open_the_printed_address)
  assert cli.main(["view", "--run", str(viewed_run[0]), "--edit", str(viewed_edit),
                   "--port", "8097"]) == 0
  assert re.fullmatch(r"http://127\.0\.0\.1:\d+/\?token=[\w-]{43}", seen["url"]), seen["url"]
  assert (seen["with"], seen["without"]) == (200, 403)


@pytest.mark.slow
def test_each_viewer_draws_its_own_token(viewer):
  assert viewer.token != access.new_token()
  assert viewer.url == f"{own_origin(viewer)}/?token={viewer.token}"


@pytest.mark.parametrize("host", ["0.0.0.0", "::", "192.168.1.5", "workstation.lan"])
def test_serving_other_machines_is_said_plainly(host):
  said = command.announcement("http://127.0.0.1:8080/?token=T", host, 8080, "E")
  assert "any machine that can reach this one on port 8080 can connect" in said
  assert "with the token" in said
  if host in ("0.0.0.0", "::"):
    assert "every network interface" in said


@pytest.mark.parametrize("host", ["127.0.0.1", "localhost", "::1", "127.0.1.1"])
def test_serving_this_machine_only_warns_of_nothing(host):
  said = command.announcement("http://127.0.0.1:8080/?token=T", host, 8080, "E")
  assert said.count("\n") == 0 and "?token=T" in said


def request(host: str, origin: str | None = None, query: str = "?token=T") -> tuple:
  headers = Headers(Host=host, Upgrade="websocket")
  if origin is not None:
    headers["Origin"] = origin
  return headers, f"/{query}"


@pytest.mark.parametrize("served, host, origin, allowed", [
    # A loopback server: its page under any of this machine's names; through an SSH tunnel
    # the page and socket share the tunnel's port.
    ("127.0.0.1", "127.0.0.1:8080", "http://localhost:8080", True),
    ("127.0.0.1", "[::1]:8080", "http://[::1]:8080", True),
    ("127.0.0.1", "localhost:9000", "http://localhost:9000", True),
    ("127.0.0.1", "localhost:9000", "http://localhost:8080", False),
    ("127.0.0.1", "workstation.lan:8080", "http://workstation.lan:8080", False),
    ("127.0.0.1", "127.0.0.1:8080", "https://127.0.0.1:8080", False),
    # Every interface: any name this machine goes by, the page's own.
    ("0.0.0.0", "workstation.lan:8080", "http://workstation.lan:8080", True),
    ("0.0.0.0", "workstation.lan:8080", "http://evil.example:8080", False),
    ("0.0.0.0", "workstation.lan:8080", "http://workstation.lan", False),
])
def test_the_gate_admits_only_the_viewers_own_page(served, host, origin, allowed):
  reason = access.Gate(served, "T").refusal(*request(host, origin))
  assert (reason is None) == allowed, reason


def test_the_gate_refuses_doubled_headers():
  headers, path = request("127.0.0.1:8080", "http://127.0.0.1:8080")
  headers["Host"] = "127.0.0.1:8080"  # Headers add: now two.
  assert "2 Host headers" in access.Gate("127.0.0.1", "T").refusal(headers, path)
