"""Who may open `signerf view`'s page and websocket: the viewer's own page, with its token.

Without a check, any web page the user has open could open a websocket to the viewer (browsers
let a page connect to any address) and drive it: set the prompt, press Save, write EDIT/
config.gin. So, as Jupyter does, each viewer draws a random token, printed in the address
`signerf view` shows (http://127.0.0.1:8080/?token=...), and every request must carry it:

  * the page: `?token=` in its address. Its answer also sets a cookie with the token, because
    viser's page opens its websocket on the page's address without the query string.
  * the websocket: the token (the cookie, or `?token=`), and an Origin header saying the page
    that opened it came from the address the socket went to (its Host header, port included;
    for a loopback server localhost, 127.0.0.1 and ::1 name one machine). A browser does not
    let a page forge its Origin, and sends the SameSite=Strict cookie from no other site's page
    (but from another port of the same host it does: there the Origin alone refuses it).

For a loopback server the Host header must also name this machine, so a site whose name is made
to resolve to 127.0.0.1 (DNS rebinding) is refused even before its lack of a token.

viser (1.1) has no option for this: it starts its websocket server (`websockets`) itself, inside
`ViserServer`, with a `process_request` hook of its own that serves the page. `serve` wraps that
hook with the check while viser starts it (see `serve`).
"""

from __future__ import annotations

import contextlib
import http
import http.cookies
import io
import ipaddress
import secrets
import sys
import threading
import urllib.parse

TOKEN_PARAMETER = "token"
WILDCARD_HOSTS = ("", "0.0.0.0", "::")


def new_token() -> str:
  """A fresh random token (43 URL-safe characters, 256 bits)."""
  return secrets.token_urlsafe(32)


def is_loopback(host: str) -> bool:
  """Whether serving on `host` reaches only this machine (localhost, 127.x.y.z, ::1)."""
  host = host.strip("[]").lower()
  if host == "localhost":
    return True
  try:
    return ipaddress.ip_address(host).is_loopback
  except ValueError:  # A machine's name: it may be reached from elsewhere.
    return False


def browser_url(host: str, port: int, token: str) -> str:
  """The address to open: `host`, or this machine's loopback address for a wildcard host (every
  interface; a browser may refuse to open 0.0.0.0), with the token."""
  host = {"": "127.0.0.1", "0.0.0.0": "127.0.0.1", "::": "::1"}.get(host, host)
  netloc = f"[{host}]" if ":" in host else host
  return f"http://{netloc}:{port}/?{urllib.parse.urlencode({TOKEN_PARAMETER: token})}"


def cookie_name(port: int) -> str:
  """The name of the token's cookie for the page at `port` (the port in the browser's address).

  Browsers share a host's cookies among its ports: one name per port keeps two viewers on one
  machine (or two tunnels) from overwriting each other's token.
  """
  return f"signerf_view_token_{port}"


def _split_netloc(netloc: str, default_port: int) -> tuple[str, int] | None:
  """(lower-case host name, port) of `host[:port]`, or None when it does not parse."""
  try:
    parts = urllib.parse.urlsplit("//" + netloc)
    if not parts.hostname:
      return None
    return parts.hostname.lower(), parts.port or default_port
  except ValueError:  # A port out of range or not a number.
    return None


def _request_token(path: str, cookies: list[str], port: int) -> tuple[str | None, str | None]:
  """(the token in the query of `path`, the token in the cookies) of a request."""
  query = urllib.parse.parse_qs(urllib.parse.urlsplit(path).query).get(TOKEN_PARAMETER, [None])
  jar = http.cookies.SimpleCookie()
  for header in cookies:
    try:
      jar.load(header)
    except http.cookies.CookieError:  # A malformed cookie header: as if it were absent.
      pass
  cookie = jar.get(cookie_name(port))
  return query[0], None if cookie is None else cookie.value


class Gate:
  """The check of every request to one viewer: the page and the websocket."""

  def __init__(self, host: str, token: str):
    self.host, self.token = host, token
    self.loopback = is_loopback(host)
    self._reported: set[str] = set()

  def _names_this_machine(self, name: str) -> bool:
    # A loopback server is reached only by this machine's own names; any other server by any
    # name the network gives this machine (the token guards it).
    return not self.loopback or is_loopback(name)

  def refusal(self, headers, path: str) -> str | None:
    """Why the request (its `headers`, websockets' Headers, and `path` with its query) is
    refused, or None when it is let through."""
    for name in ("Host", "Origin"):
      if len(headers.get_all(name)) > 1:
        return f"{len(headers.get_all(name))} {name} headers"
    host = _split_netloc(headers.get("Host", ""), 80)
    if host is None or not self._names_this_machine(host[0]):
      return f"the Host header {headers.get('Host')!r} does not name this viewer"
    origin = headers.get("Origin")
    if origin is None and "websocket" in ",".join(headers.get_all("Upgrade")).lower():
      return "a websocket without an Origin header"
    if origin is not None:
      parts = urllib.parse.urlsplit(origin)
      page = _split_netloc(parts.netloc, 80) if parts.scheme == "http" else None
      same_machine = (self.loopback and page is not None and is_loopback(page[0])
                      and is_loopback(host[0]))
      if page is None or page[1] != host[1] or (page[0] != host[0] and not same_machine):
        return f"Origin {origin!r} is not the viewer's own page"
    query_token, cookie_token = _request_token(path, headers.get_all("Cookie"), host[1])
    if not (self._is_token(query_token) or self._is_token(cookie_token)):
      return ("no token" if query_token is None and cookie_token is None else "a wrong token")
    return None

  def _is_token(self, given: str | None) -> bool:
    return given is not None and secrets.compare_digest(given.encode(), self.token.encode())

  def wrap(self, process_request):
    """websockets' `process_request` hook: `process_request` (viser's, which serves the page)
    behind the check. A refused request is answered 403 with the reason; the page asked for
    with the right `?token=` sets the token's cookie for its websocket."""

    def gated(connection, request):
      reason = self.refusal(request.headers, request.path)
      if reason is not None:
        self._report(reason, request)
        return connection.respond(http.HTTPStatus.FORBIDDEN, f"signerf view: refused: {reason}."
                                  " Open the address `signerf view` printed (with ?token=).\n")
      response = process_request(connection, request) if process_request else None
      query_token, _ = _request_token(request.path, [], 0)
      if response is not None and self._is_token(query_token):
        _, port = _split_netloc(request.headers["Host"], 80)
        response.headers["Set-Cookie"] = (f"{cookie_name(port)}={self.token}; Path=/; "
                                          "HttpOnly; SameSite=Strict")
        # The address holds the token: sent to no other site as a Referer.
        response.headers["Referrer-Policy"] = "no-referrer"
      return response

    return gated

  def _report(self, reason: str, request) -> None:
    # Once per reason and Origin: a stale page retries its websocket every few seconds.
    origin = request.headers.get("Origin")
    key = f"{reason} {origin}"
    if key not in self._reported:
      self._reported.add(key)
      print(f"signerf view: refused {request.path.split('?')[0]!r}"
            f"{f' from Origin {origin}' if origin else ''}: {reason}", file=sys.stderr,
            flush=True)


# One viser server starts at a time: `serve` stands in for websockets' own `serve` meanwhile.
_STARTING = threading.Lock()


def serve(host: str, port: int, token: str):
  """A viser server on `host`:`port` (or the next free port) whose page and websocket ask for
  `token` and refuse a websocket from any page but the viewer's own.

  viser starts its `websockets` server inside `ViserServer`'s constructor, on a thread of its own,
  through `websockets.asyncio.server.serve`, passing its page server as `process_request`. For
  the length of that constructor (viser waits for the server to listen before it returns),
  `serve` is replaced by one that wraps viser's hook with the gate; only calls passing viser's
  hook are touched, and a viser whose server no longer starts this way is refused rather than
  served unguarded.
  """
  # Here, not at the top: the command line imports this module to build its parser.
  import viser  # pylint: disable=g-import-not-at-top
  import websockets.asyncio.server  # pylint: disable=g-import-not-at-top
  gate = Gate(host, token)
  original = websockets.asyncio.server.serve
  wrapped = []

  def gated_serve(*args, process_request=None, **kwargs):
    if getattr(process_request, "__qualname__", "").endswith("viser_http_server"):
      process_request = gate.wrap(process_request)
      wrapped.append(True)
    return original(*args, process_request=process_request, **kwargs)

  with _STARTING:
    websockets.asyncio.server.serve = gated_serve
    try:
      # viser prints its address, without the token, whatever `verbose` says: a second address
      # that only answers 403 beside the one `signerf view` prints. Nothing else writes to
      # stdout while the server starts.
      with contextlib.redirect_stdout(io.StringIO()):
        server = viser.ViserServer(host=host, port=port, verbose=False)
    finally:
      websockets.asyncio.server.serve = original
  if not wrapped:
    server.stop()
    raise RuntimeError(f"viser {viser.__version__} did not start its server through "
                       "websockets.asyncio.server.serve with its page server: signerf view "
                       "cannot check who connects (signerf_jax/viewer/access.py)")
  return server
