"""The browser viewer's page: a viser server behind a guard, and what it draws.

:class:`ViewGuard` is the only socket a browser reaches. It listens on ``host:port`` (127.0.0.1 by default)
and passes a connection on to the viser server, which listens on an ephemeral port of 127.0.0.1, only when

* the request carries the viewer's random token: in the page's URL (``/?token=…``), which the guard answers
  by setting a cookie (``HttpOnly``, ``SameSite=Strict``, named after the port), or in that cookie;
* its ``Host`` header names the viewer's own address (a page reached by DNS rebinding names its own host; not
  checked when listening on every address, 0.0.0.0 or ::);
* a WebSocket handshake's ``Origin`` header is the viewer's own origin (any web page may open a WebSocket to
  127.0.0.1; the browser sets ``Origin`` and a page cannot change it); listening on every address, the origin
  of the address the page was loaded from.

Everything else gets ``403 Forbidden`` and never reaches viser. The guard forwards one HTTP request per
connection (it reads no further requests from a connection it passed on), so a kept-alive connection cannot
carry a second request past the check. Not protected: a process of the same machine that can read the URL
(the token is printed on the terminal), and traffic on other addresses than 127.0.0.1, which is plain HTTP
(the token is visible to whoever can read the network).

:class:`Viewer` draws a :class:`Picture` (a frame's surfaces, particles, springs, pins and colliders, per
world) with the display controls every viewer has: what is shown, the colour (solid, speed, any per-vertex
primvar), the worlds laid out or one at a time, and the camera framing the scene. The file viewer
(:mod:`~warpspring.app.viewer_file`) and the live viewer (:mod:`~warpspring.app.viewer_live`) feed it.
viser is an optional dependency (``pip install 'warpspring[view]'``).
"""

from __future__ import annotations

import asyncio
import contextlib
import http.cookies
import io
import logging
import secrets
import threading
import urllib.parse
from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError

#: The colours of the viewer [0-255 RGB].
SURFACE_COLOR = (217, 84, 56)
COLLIDER_COLOR = (150, 165, 185)
SPRING_COLOR = (40, 40, 40)
PARTICLE_COLOR = (30, 90, 200)
PIN_COLOR = (20, 20, 20)
#: The largest request head the guard reads [bytes].
MAX_HEAD = 16384


def require_viser():
    """The viser module, or a ConfigError saying how to install it."""
    try:
        import viser  # optional: viser
    except ImportError:
        raise ConfigError("the viewer needs viser: pip install 'warpspring[view]'") from None
    return viser


# -- the guard ------------------------------------------------------------------------------------------------


class ViewGuard:
    """A token and Origin check in front of a local server (see the module's docstring).

    Args:
        upstream: the port of the server behind it, on 127.0.0.1.
        host: the address to listen on.
        port: the port to listen on (0: any free one).
        token: the secret the URL carries (default: 32 random bytes, URL-safe).
    """

    def __init__(self, upstream: int, *, host: str = "127.0.0.1", port: int = 0, token: str | None = None):
        self.upstream = upstream
        self.host = host
        self.token = token or secrets.token_urlsafe(32)
        self.refused = 0  # requests refused so far
        self.relayed_ports: set[int] = set()  # the local ports of the guard's open connections to the upstream
        self._loop = asyncio.new_event_loop()
        self._server = None
        ready = threading.Event()
        failure: list = []

        def serve():
            asyncio.set_event_loop(self._loop)
            try:
                self._server = self._loop.run_until_complete(
                    asyncio.start_server(self._handle, host, port, limit=MAX_HEAD))
            except OSError as exc:
                failure.append(exc)
                ready.set()
                return
            ready.set()
            self._loop.run_forever()

        self._thread = threading.Thread(target=serve, name="warpspring-view-guard", daemon=True)
        self._thread.start()
        ready.wait()
        if failure:
            raise ConfigError(f"the viewer cannot listen on {host}:{port}: {failure[0].strerror or failure[0]}; "
                              "choose another --view-port")
        self.port = self._server.sockets[0].getsockname()[1]
        shown = f"[{host}]" if ":" in host else host
        self.cookie = f"warpspring_view_{self.port}"
        self.origins = {f"http://{shown}:{self.port}"} | (
            {f"http://localhost:{self.port}", f"http://127.0.0.1:{self.port}"} if host in ("127.0.0.1", "localhost")
            else set())
        self.hosts = {o[len("http://"):] for o in self.origins}

    @property
    def url(self) -> str:
        """The page's address, with the token."""
        shown = f"[{self.host}]" if ":" in self.host else self.host
        if self.host in ("0.0.0.0", "::"):
            shown = "127.0.0.1"
        return f"http://{shown}:{self.port}/?token={self.token}"

    def check(self, head: bytes) -> tuple[bool, str]:
        """Whether a request head may pass, and the cookie to set (empty: none)."""
        try:
            lines = head.decode("latin-1").split("\r\n")
            method, target, _ = lines[0].split(" ", 2)
        except ValueError:
            return False, ""
        headers = {}
        for line in lines[1:]:
            name, sep, value = line.partition(":")
            if sep:
                headers[name.strip().lower()] = value.strip()
        if self.host not in ("0.0.0.0", "::") and headers.get("host") not in self.hosts:
            return False, ""
        query = urllib.parse.parse_qs(urllib.parse.urlsplit(target).query)
        cookies = http.cookies.SimpleCookie()
        try:
            cookies.load(headers.get("cookie", ""))
        except http.cookies.CookieError:
            pass
        given = [t for t in query.get("token", [])] + ([cookies[self.cookie].value] if self.cookie in cookies else [])
        if not any(secrets.compare_digest(t, self.token) for t in given):
            return False, ""
        if headers.get("upgrade", "").lower() == "websocket":
            origin = headers.get("origin")
            wildcard = self.host in ("0.0.0.0", "::")  # any address of the machine: the page's own, as asked
            if origin not in self.origins and not (wildcard and origin == f"http://{headers.get('host')}"):
                return False, ""
        return True, "" if self.cookie in cookies else self.cookie

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            head = await reader.readuntil(b"\r\n\r\n")
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, ConnectionError):
            writer.close()
            return
        allowed, set_cookie = self.check(head)
        if not allowed:
            self.refused += 1
            writer.write(b"HTTP/1.1 403 Forbidden\r\nContent-Length: 0\r\nConnection: close\r\n\r\n")
            await _close(writer)
            return
        try:
            up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.upstream)
        except OSError:
            await _close(writer)
            return
        local = up_writer.get_extra_info("sockname")[1]
        self.relayed_ports.add(local)
        upgrade = b"\r\nupgrade: websocket" in head.lower()
        up_writer.write(head)
        pumps = [self._pump(up_reader, writer, set_cookie=set_cookie)]
        if upgrade:  # the WebSocket's frames follow the handshake; a plain request has no body (GET)
            pumps.append(self._pump(reader, up_writer))
        try:
            await asyncio.gather(*pumps, return_exceptions=True)
        finally:
            self.relayed_ports.discard(local)
            await _close(writer)
            await _close(up_writer)

    async def _pump(self, reader, writer, *, set_cookie: str = "") -> None:
        first = True
        try:
            while True:
                data = await reader.read(1 << 20)  # a frame's message in few reads
                if not data:
                    break
                if first and set_cookie:  # the page's response: the token goes into a cookie for what follows
                    end = data.find(b"\r\n")
                    if end > 0:
                        cookie = (f"\r\nSet-Cookie: {set_cookie}={self.token}; Path=/; HttpOnly; SameSite=Strict"
                                  .encode())
                        data = data[:end] + cookie + data[end:]
                first = False
                writer.write(data)
                await writer.drain()
        except (ConnectionError, asyncio.CancelledError):
            pass
        finally:
            try:
                writer.write_eof()
            except (OSError, RuntimeError):
                pass

    def close(self) -> None:
        """Stop listening and end the connections passed on."""
        async def shutdown():
            self._server.close()
            tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            self._loop.stop()

        if self._loop.is_running():
            asyncio.run_coroutine_threadsafe(shutdown(), self._loop)
            self._thread.join(timeout=5)


async def _close(writer) -> None:
    try:
        writer.close()
        await writer.wait_closed()
    except (ConnectionError, OSError):
        pass


# -- what a frame shows ---------------------------------------------------------------------------------------


@dataclass
class Surface:
    """A triangulated surface of one frame: ``points`` [m] shape [V, 3], ``faces`` int32 [F, 3], per-vertex
    ``values`` (name → float [V]: "speed" [m/s], primvars)."""

    name: str
    points: np.ndarray
    faces: np.ndarray
    values: dict = field(default_factory=dict)


@dataclass
class Picture:
    """What one frame shows, per world (key: the world's name, "" for a file of one world).

    Attributes:
        surfaces: world → list of :class:`Surface` (cloth, soft-body skins).
        particles: world → positions [m], shape [N, 3].
        springs: world → segment ends [m], shape [S, 2, 3].
        pins: world → pinned positions [m], shape [P, 3].
        colliders: world → list of :class:`Surface` (colliders as triangles).
        time: the frame's time [s].
    """

    surfaces: dict = field(default_factory=dict)
    particles: dict = field(default_factory=dict)
    springs: dict = field(default_factory=dict)
    pins: dict = field(default_factory=dict)
    colliders: dict = field(default_factory=dict)
    time: float = 0.0

    def only(self, worlds) -> Picture:
        """The picture of ``worlds`` alone."""
        def pick(table):
            return {w: v for w, v in table.items() if w in worlds}

        return Picture(pick(self.surfaces), pick(self.particles), pick(self.springs), pick(self.pins),
                       pick(self.colliders), self.time)

    def worlds(self) -> list[str]:
        return sorted(set(self.surfaces) | set(self.particles) | set(self.springs) | set(self.colliders))

    def bounds(self, *, colliders: bool = False) -> tuple[np.ndarray, np.ndarray] | None:
        """The box around what moves (and the colliders if asked) [m], or None when empty."""
        parts = [s.points for v in self.surfaces.values() for s in v] + list(self.particles.values())
        if colliders or not any(len(p) for p in parts):
            parts += [s.points for v in self.colliders.values() for s in v if len(s.points) < 1e5]
        parts = [p for p in parts if len(p)]
        if not parts:
            return None
        every = np.concatenate(parts)
        return every.min(axis=0), every.max(axis=0)


def colormap(values: np.ndarray, low: float, high: float) -> np.ndarray:
    """Values → RGB [0-255] uint8, shape [N, 3]: blue (low) through white to red (high)."""
    t = np.clip((values - low) / (high - low) if high > low else np.zeros_like(values), 0.0, 1.0)[:, None]
    blue, white, red = np.array([59, 76, 192]), np.array([221, 221, 221]), np.array([180, 4, 38])
    rgb = np.where(t < 0.5, blue + (white - blue) * (2 * t), white + (red - white) * (2 * t - 1))
    return rgb.astype(np.uint8)


class Viewer:
    """A viser page behind a :class:`ViewGuard` that shows :class:`Picture` objects.

    Args:
        host: the address to listen on (127.0.0.1 by default; another address lets other machines in,
            over plain HTTP).
        port: the port (0: any free one).
        up_axis: the scene's up axis, "Y" or "Z".
        title: shown at the top of the controls.
    """

    def __init__(self, *, host: str = "127.0.0.1", port: int = 0, up_axis: str = "Z", title: str = "warpspring"):
        viser = require_viser()
        with contextlib.redirect_stdout(io.StringIO()):  # viser's banner names its own port, not the page's
            self.server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
        try:
            self.guard = ViewGuard(self.server.get_port(), host=host, port=port)
        except ConfigError:
            self.server.stop()
            raise
        self._refuse_unguarded()
        self.server.request_share_url = _no_share  # no tunnel to a public relay around the guard
        self.server.gui.configure_theme(show_share_button=False)
        self.server.scene.set_up_direction("+z" if up_axis.upper() == "Z" else "+y")
        self.up_axis = up_axis.upper()
        self.lock = threading.Lock()  # one show() at a time
        self._handles: dict = {}
        self._shapes: dict = {}
        self._sent: dict = {}  # name → the points array last sent
        self._faces: dict = {}  # name → the faces array its mesh was made with
        self._color_range: tuple[float, float] | None = None
        self._framed = False
        self._last: Picture | None = None
        gui = self.server.gui
        gui.add_markdown(f"**{title}**")
        with gui.add_folder("Display"):
            self.color_by = gui.add_dropdown("colour by", ["solid", "speed"], initial_value="solid")
            self.show_surfaces = gui.add_checkbox("surfaces", True)
            self.show_springs = gui.add_checkbox("springs", False)
            self.show_particles = gui.add_checkbox("particles", False)
            self.show_pins = gui.add_checkbox("pins", True)
            self.show_colliders = gui.add_checkbox("colliders", True)
            self.world = gui.add_dropdown("worlds", ["all, laid out"], initial_value="all, laid out")
            self.frame_camera = gui.add_button("frame the scene")
        for control in (self.color_by, self.show_surfaces, self.show_springs, self.show_particles, self.show_pins,
                        self.show_colliders, self.world):
            control.on_update(lambda _: self.redraw())
        self.color_by.on_update(lambda _: setattr(self, "_color_range", None))
        self.world.on_update(lambda _: self.frame(self._last))  # one world at a time: the camera follows
        self.frame_camera.on_click(lambda _: self.frame(self._last))

    @property
    def url(self) -> str:
        """The page's address, with its token."""
        return self.guard.url

    def _refuse_unguarded(self) -> None:
        """Close every WebSocket to viser's own port that did not come through the guard (a page may scan the
        ports of 127.0.0.1), before viser reads a message from it: the check runs first among the connection's
        callbacks, and raising there ends the connection's handler before its reader starts."""
        websock = self.server._websock_server  # viser 1.x's WebSocket server (no public hook runs this early)
        guard = self.guard

        async def check(connection) -> None:
            raw = websock._live_connections.get(connection.client_id)
            if raw is None or raw.remote_address[1] not in guard.relayed_ports:
                guard.refused += 1
                raise ConnectionRefusedError("a WebSocket that did not pass the viewer's guard")

        websock._client_connect_cb.insert(0, check)
        logging.getLogger("websockets.server").addFilter(_quiet_refusals)

    def close(self) -> None:
        self.guard.close()
        with contextlib.redirect_stdout(io.StringIO()):
            self.server.stop()

    def redraw(self) -> None:
        if self._last is not None:
            self.show(self._last)

    def frame(self, picture: Picture | None) -> None:
        """Point every client's camera (and the initial camera) at the moving parts of the worlds shown."""
        if picture is not None and self.world.value != "all, laid out":
            picture = picture.only([self.world.value])
        box = picture.bounds() if picture is not None else None
        if box is None:
            return
        low, high = box
        centre = 0.5 * (low + high)
        radius = max(0.5 * float(np.linalg.norm(high - low)), 0.05)
        up = np.array([0.0, 0.0, 1.0]) if self.up_axis == "Z" else np.array([0.0, 1.0, 0.0])
        side = np.array([1.0, -1.6, 0.0]) if self.up_axis == "Z" else np.array([1.0, 0.0, 1.6])
        towards = side / np.linalg.norm(side) + 0.6 * up
        eye = centre + 2.8 * radius * towards / np.linalg.norm(towards)
        camera = self.server.initial_camera
        camera.position, camera.look_at = tuple(eye), tuple(centre)
        for client in self.server.get_clients().values():
            client.camera.position, client.camera.look_at = tuple(eye), tuple(centre)

    def show(self, picture: Picture) -> None:
        """Draw ``picture``, updating what was drawn before in place where its shape is unchanged."""
        with self.lock:
            self._last = picture
            worlds = picture.worlds()
            options = ["all, laid out"] + [w for w in worlds if w]
            if tuple(self.world.options) != tuple(options):
                self.world.options = options
            names = {"solid", "speed"} | {k for v in picture.surfaces.values() for s in v for k in s.values}
            if set(self.color_by.options) != names:
                self.color_by.options = ["solid", "speed"] + sorted(names - {"solid", "speed"})
            shown = worlds if self.world.value == "all, laid out" else [self.world.value]
            mode = self.color_by.value
            if mode != "solid":
                every = [s.values[mode] for w in shown for s in picture.surfaces.get(w, []) if mode in s.values]
                if every:
                    top = float(max(np.max(v) for v in every if len(v)) if any(len(v) for v in every) else 0.0)
                    low = float(min(np.min(v) for v in every if len(v)) if any(len(v) for v in every) else 0.0)
                    lo, hi = self._color_range or (low, top)
                    self._color_range = (min(lo, low), max(hi, top))  # kept over frames: colours compare
            seen = set()
            with self.server.atomic():
                for world in worlds:
                    visible = world in shown
                    for s in picture.surfaces.get(world, []):
                        seen.add(self._surface(f"/{world or 'world'}/surfaces/{s.name}", s, mode,
                                               visible and self.show_surfaces.value))
                    for s in picture.colliders.get(world, []):
                        seen.add(self._mesh(f"/{world or 'world'}/colliders/{s.name}", s, COLLIDER_COLOR,
                                            visible and self.show_colliders.value, opacity=0.55))
                    points = picture.particles.get(world)
                    if points is not None and len(points):
                        seen.add(self._points(f"/{world or 'world'}/particles", points, PARTICLE_COLOR,
                                              visible and self.show_particles.value, size=0.012))
                    pins = picture.pins.get(world)
                    if pins is not None and len(pins):
                        seen.add(self._points(f"/{world or 'world'}/pins", pins, PIN_COLOR,
                                              visible and self.show_pins.value, size=0.04))
                    springs = picture.springs.get(world)
                    if springs is not None and len(springs):
                        seen.add(self._segments(f"/{world or 'world'}/springs", springs,
                                                visible and self.show_springs.value))
                for name in set(self._handles) - seen:
                    self._handles.pop(name).remove()
                    self._shapes.pop(name, None)
                    self._sent.pop(name, None)
            if not self._framed:
                self._framed = True
                self.frame(picture)

    def _surface(self, name: str, surface: Surface, mode: str, visible: bool) -> str:
        if mode == "solid" or mode not in surface.values:
            return self._mesh(name, surface, SURFACE_COLOR, visible)
        import trimesh  # optional: trimesh (a vertex-coloured mesh travels as glTF)

        low, high = self._color_range
        mesh = trimesh.Trimesh(surface.points, surface.faces, process=False,
                               vertex_colors=colormap(np.asarray(surface.values[mode]), low, high))
        self._drop(name, "glb")
        self._handles[name] = self.server.scene.add_mesh_trimesh(name, mesh, visible=visible)
        self._shapes[name] = ("glb",)
        return name

    def _drop(self, name: str, kind) -> None:
        if name in self._handles and self._shapes.get(name) != kind:
            self._handles.pop(name).remove()

    def _mesh(self, name: str, surface: Surface, color, visible: bool, *, opacity: float | None = None) -> str:
        shape = ("mesh", surface.faces.shape)
        handle = self._handles.get(name)
        faces = self._faces.get(name)
        if (handle is not None and self._shapes.get(name) == shape
                and (faces is surface.faces or np.array_equal(faces, surface.faces))):  # the same object: no compare
            self._faces[name] = surface.faces
            if visible and self._sent.get(name) is not surface.points:  # a hidden or unchanged layer is not sent
                handle.vertices = surface.points.astype(np.float32, copy=False)
                self._sent[name] = surface.points
            if handle.visible != visible:
                handle.visible = visible
            return name
        self._drop(name, "mesh anew")
        self._sent[name] = surface.points
        self._faces[name] = surface.faces
        self._handles[name] = self.server.scene.add_mesh_simple(
            name, surface.points.astype(np.float32), surface.faces.astype(np.uint32), color=color, side="double",
            opacity=opacity, visible=visible)
        self._shapes[name] = shape
        return name

    def _layer(self, name: str, shape: tuple, values: np.ndarray, visible: bool, add) -> str:
        """Show ``values`` (points or segments, float32 on the wire) as the layer ``name``: updated in place while
        its ``shape`` is unchanged (a hidden layer's data is not sent), else made anew by ``add(values)``."""
        handle = self._handles.get(name)
        if handle is not None and self._shapes.get(name) == shape:
            if visible:
                handle.points = values.astype(np.float32, copy=False)
            if handle.visible != visible:
                handle.visible = visible
            return name
        self._drop(name, shape)
        self._handles[name] = add(values.astype(np.float32))
        self._shapes[name] = shape
        return name

    def _points(self, name: str, points: np.ndarray, color, visible: bool, *, size: float) -> str:
        return self._layer(name, ("points", len(points)), points, visible,
                           lambda values: self.server.scene.add_point_cloud(
                               name, values, colors=color, point_size=size, point_shape="circle", visible=visible))

    def _segments(self, name: str, segments: np.ndarray, visible: bool) -> str:
        return self._layer(name, ("segments", len(segments)), segments, visible,
                           lambda values: self.server.scene.add_line_segments(
                               name, values, colors=SPRING_COLOR, thickness=1.0, thickness_units="screen",
                               visible=visible))


def _no_share(*args, **kwargs) -> None:
    """viser's share-URL request, refused."""
    return None


def _quiet_refusals(record: logging.LogRecord) -> bool:
    """websockets' log without the traceback of a connection the guard's check refused (it is counted)."""
    return not (record.exc_info and isinstance(record.exc_info[1], ConnectionRefusedError))
