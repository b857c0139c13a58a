"""The browser viewer: its guard (token, Origin, Host; viser's own port closed to anything but the guard), the
USD reader against the states written, the stiffness clamp, and headless Chromium driving both pages: a file's
canvas is drawn and the frame slider changes it; the live page's gravity reaches the simulation, read back
from the model and from the motion of the cloth's centre of mass.

The browser tests need viser, selenium and a Chromium with its driver (Debian's ``chromium`` and
``chromium-driver``; ``.ci/run`` installs them); where one is missing they are skipped with the reason.
"""

import io
import shutil
import time

import numpy as np
import pytest

import warpspring as ws
from helpers import hanging_cloth, write_scene

viser = pytest.importorskip("viser", reason="the viewer needs viser: pip install 'warpspring[view]'")

from warpspring.app.viewer import ViewGuard, colormap  # noqa: E402
from warpspring.app.viewer_file import FileView, UsdFrames, triangulate  # noqa: E402
from warpspring.app.viewer_live import STIFFNESS_RANGE, LiveView, stiffness_limit  # noqa: E402
from warpspring.app.cli import main  # noqa: E402
from warpspring.io.usd import UsdWriter  # noqa: E402

FRAMES = 6


@pytest.fixture(scope="module")
def cloth_file(tmp_path_factory):
    """A 10 × 10 cloth written by UsdWriter over FRAMES frames in which it sags by a known amount and moves
    sideways (positions and velocities set by hand): the file and each frame's positions and velocities."""
    model, _ = hanging_cloth("cpu", n=10, ground=True)
    state = model.state()
    q0 = state.particle_q.numpy().astype(np.float64)
    path = str(tmp_path_factory.mktemp("view") / "cloth.usdc")
    frames = []
    with UsdWriter(path, model, fps=30.0, primvars=("pinned",), springs=True) as usd:
        for k in range(FRAMES + 1):
            r = np.linalg.norm(q0[:, :2], axis=1)
            q = q0 + np.stack([0.1 * k + 0 * r, 0 * r, -0.08 * k * (1.0 - r / r.max())], axis=1)
            v = np.stack([np.full_like(r, 3.0), 0 * r, -2.4 * (1.0 - r / r.max())], axis=1) * (k > 0)
            state.particle_q.assign(q.astype(np.float32))
            state.particle_qd.assign(v.astype(np.float32))
            usd.write_frame(state)
            frames.append((q.astype(np.float32), v.astype(np.float32)))
    return path, frames


def test_triangulate_fans_polygons():
    counts = np.array([4, 3])
    indices = np.array([0, 1, 2, 3, 4, 5, 6])
    tris = {tuple(t) for t in triangulate(counts, indices)}
    assert tris == {(0, 1, 2), (0, 2, 3), (4, 5, 6)}


def test_usd_frames_read_what_was_written(cloth_file):
    path, frames = cloth_file
    reader = UsdFrames(path)
    assert (reader.first, reader.last) == (0, FRAMES)
    for k in (0, 3, FRAMES):
        picture = reader.picture(k)
        (cloth,) = picture.surfaces[""]
        q, v = frames[k]
        # The file stores float32 positions: read back exactly, with no transform on a one-world file.
        np.testing.assert_array_equal(cloth.points.astype(np.float32), q)
        np.testing.assert_allclose(cloth.values["speed"], np.linalg.norm(v.astype(np.float64), axis=1), rtol=1e-6)
        # The two pinned top corners, from the pinned primvar.
        assert len(picture.pins[""]) == 2
        assert {c.name for c in picture.colliders[""]} == {"ground"}
        # 10 × 10 grid: 2 · 9 · 9 triangles.
        assert cloth.faces.shape == (162, 3)
        assert len(picture.springs[""]) > 0


def test_colormap_ends():
    rgb = colormap(np.array([0.0, 0.5, 1.0, 2.0]), 0.0, 1.0)
    np.testing.assert_array_equal(rgb[0], [59, 76, 192])
    np.testing.assert_array_equal(rgb[1], [221, 221, 221])
    np.testing.assert_array_equal(rgb[2], rgb[3])  # clipped


def test_stiffness_limit_follows_the_step():
    # ω grows as √scale, so dt stays stable while scale ≤ (dt_stable / dt)².
    assert stiffness_limit(1.0e-3, 1.5e-3) == pytest.approx(2.25)
    assert stiffness_limit(1.0e-3, 1.0e-3) == pytest.approx(1.0)
    assert stiffness_limit(1.0e-3, 0.5e-3) == 1.0  # already past the limit: no stiffer
    assert stiffness_limit(1.0e-3, float("inf")) == STIFFNESS_RANGE[1]
    assert stiffness_limit(1.0e-3, 1.0) == STIFFNESS_RANGE[1]


def _ws_status(url, origin=None, cookie=None):
    from websockets.sync.client import connect

    headers = {"Cookie": cookie} if cookie else None
    try:
        with connect(url, subprotocols=[f"viser-v{viser.__version__}"], origin=origin, additional_headers=headers,
                     open_timeout=5) as ws_:
            ws_.recv(timeout=5)
            return "open"
    except Exception as exc:  # the refusal's kind is what is compared
        return type(exc).__name__


def test_guard_refuses_without_token_origin_or_host(cloth_file):
    import urllib.error
    import urllib.request

    view = FileView(cloth_file[0], follow=False)
    try:
        guard = view.viewer.guard
        own = f"http://127.0.0.1:{guard.port}"
        base = f"ws://127.0.0.1:{guard.port}/"
        assert _ws_status(base + f"?token={guard.token}", origin=own) == "open"
        assert _ws_status(base, origin=own, cookie=f"{guard.cookie}={guard.token}") == "open"
        refused = guard.refused
        assert _ws_status(base, origin=own) == "InvalidStatus"  # no token
        assert _ws_status(base + "?token=wrong", origin=own) == "InvalidStatus"
        assert _ws_status(base + f"?token={guard.token}", origin="http://evil.example") == "InvalidStatus"
        assert _ws_status(base + f"?token={guard.token}") == "InvalidStatus"  # no Origin
        assert guard.refused == refused + 4
        # viser's own port (found by a page scanning 127.0.0.1) closes what did not come through the guard.
        assert _ws_status(f"ws://127.0.0.1:{guard.upstream}/", origin=f"http://127.0.0.1:{guard.upstream}") != "open"
        assert guard.refused == refused + 5
        # The page: the token's URL sets the cookie; a rebinding page's Host is refused.
        with urllib.request.urlopen(view.url, timeout=5) as response:
            assert response.status == 200
            assert f"{guard.cookie}={guard.token}" in response.headers["Set-Cookie"]
            assert "SameSite=Strict" in response.headers["Set-Cookie"]
        for url, headers in [(own + "/", {}), (view.url, {"Host": f"evil.example:{guard.port}"})]:
            with pytest.raises(urllib.error.HTTPError) as error:
                urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=5)
            assert error.value.code == 403
    finally:
        view.close()


# -- in a browser ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def chromium():
    """One headless Chromium for the module's browser tests (Selenium), or a skip with the reason."""
    driver = _chromium()
    yield driver
    driver.quit()


def _chromium():
    """A headless Chromium through Selenium, or a skip with the reason."""
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed (pip install selenium)")
    browser = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome") if shutil.which(n)), None)
    driver = shutil.which("chromedriver")
    if browser is None or driver is None:
        pytest.skip("no Chromium with its driver: apt-get install chromium chromium-driver")
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = browser
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader",
                 "--enable-unsafe-swiftshader", "--disable-background-networking", "--disable-dev-shm-usage",
                 "--window-size=1000,700"):
        options.add_argument(flag)
    return webdriver.Chrome(options=options, service=Service(driver))


def _canvas(driver) -> np.ndarray:
    from PIL import Image
    from selenium.webdriver.common.by import By

    png = driver.find_element(By.TAG_NAME, "canvas").screenshot_as_png
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int16)[::3, ::3]  # every 9th pixel


def _drawn_fraction(image: np.ndarray) -> float:
    """The fraction of pixels unlike the picture's most common colour (its background)."""
    flat = image.reshape(-1, 3)
    colours, counts = np.unique(flat, axis=0, return_counts=True)
    background = colours[np.argmax(counts)]
    return float(np.mean(np.abs(flat - background).sum(axis=1) > 24))


def _wait(condition, timeout=10.0, step=0.1):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(step)
    return False


@pytest.mark.slow  # 10-30 s: Chromium's start and software WebGL
def test_file_view_in_chromium(cloth_file, chromium):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    view = FileView(cloth_file[0], follow=False)
    driver = chromium
    try:
        driver.get(view.url)
        assert _wait(lambda: view.viewer.server.get_clients(), 15), "the page did not connect"
        assert _wait(lambda: _drawn_fraction(_canvas(driver)) > 0.01, 15), "the canvas stayed blank"
        time.sleep(1.0)  # the first frame's meshes settle
        before = _canvas(driver)
        slider = driver.find_element(By.CSS_SELECTOR, "[role=slider]")
        slider.click()
        slider.send_keys(Keys.END)
        assert _wait(lambda: int(view.slider.value) == FRAMES), f"slider at {view.slider.value}"
        assert _wait(lambda: np.abs(_canvas(driver) - before).sum(axis=2).astype(bool).mean() > 0.005), \
            "moving the frame slider did not change the picture"
    finally:
        view.close()


@pytest.mark.slow  # 10-30 s: Chromium's start and software WebGL
def test_live_gravity_from_chromium_reaches_the_simulation(chromium):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    # A free cloth (no pins, no drag, no ground): its centre of mass accelerates by exactly the gravity, the
    # springs' forces cancelling in pairs.
    model, _ = hanging_cloth("cpu", n=8, pin=[])
    model.gravity = (0.0, 0.0, -9.81)
    sim = ws.Simulator(model, fps=60.0, substeps=16)
    live = LiveView().attach(sim)
    driver = chromium
    try:
        driver.get(live.url)
        assert _wait(lambda: live.viewer.server.get_clients(), 15), "the page did not connect"
        assert _wait(lambda: _drawn_fraction(_canvas(driver)) > 0.005, 15), "the canvas stayed blank"
        label = driver.execute_script(
            "return Array.from(document.querySelectorAll('label')).find(l => l.textContent.startsWith('gravity'))"
            ".htmlFor")
        numbers = driver.find_elements(By.CSS_SELECTOR, "input.mantine-NumberInput-input")
        first = [n.get_attribute("id") for n in numbers].index(label)
        z = numbers[first + 2]
        z.send_keys(Keys.CONTROL, "a")
        z.send_keys("4.5", Keys.ENTER)
        z.send_keys(Keys.TAB)
        assert _wait(lambda: tuple(live.gravity.value)[2] == pytest.approx(4.5)), "the page did not send gravity"
        sim.step_frame()  # the change is applied after a frame, for the next one
        assert model.gravity == pytest.approx((0.0, 0.0, 4.5))
        v0 = sim.state.particle_qd.numpy().astype(np.float64).mean(axis=0)
        frames = 6
        for _ in range(frames):
            sim.step_frame()
        v1 = sim.state.particle_qd.numpy().astype(np.float64).mean(axis=0)
        # Δv̄ = g · t exactly but for float32 rounding of the sums (64 particles, |v| ~ 1 m/s: 1e-5 m/s).
        np.testing.assert_allclose(v1 - v0, [0.0, 0.0, 4.5 * frames / 60.0], atol=1e-4)
        # The stiffness sent from outside the advisor's range is clamped on the server.
        base = model.spring_stiffness.numpy().astype(np.float64)
        live.apply(sim, {"stiffness": 1.0e6})
        np.testing.assert_allclose(model.spring_stiffness.numpy(), base * live.stiffness_max, rtol=1e-6)
    finally:
        live.close()



def test_usd_frames_follow_a_growing_file(tmp_path):
    model, _ = hanging_cloth("cpu", n=4)
    state = model.state()
    path = str(tmp_path / "growing.usdc")
    with UsdWriter(path, model, fps=30.0) as usd:
        usd.write_frame(state)
        usd.write_frame(state)
        reader = UsdFrames(path)
        assert reader.last == 1
        assert not reader.refresh()  # unchanged on disk
        q = state.particle_q.numpy().copy()
        for k in range(3):
            time.sleep(0.01)  # a new modification time
            state.particle_q.assign(q + np.float32(0.1 * (k + 1)))
            usd.write_frame(state)
        assert reader.refresh()
        assert reader.last == 4
        (cloth,) = reader.picture(4).surfaces[""]
        np.testing.assert_array_equal(cloth.points.astype(np.float32), q + np.float32(0.3))


def test_run_with_view_writes_its_file(tmp_path):
    out = tmp_path / "viewed.usdc"
    assert main(["run", str(write_scene(tmp_path)), "-o", str(out), "--frames", "3", "-q", "--view",
                 "--view-port", "0"]) == 0
    reader = UsdFrames(out)
    assert (reader.first, reader.last) == (0, 3)


def test_live_handle_target_reaches_the_simulation():
    # A free cloth at rest, no gravity: the first step after the page moves the handle's target by d pushes the
    # grabbed particle with kp·d, and the springs' forces cancel in pairs, so the momentum is kp·d·dt exactly.
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=4, ny=4, spacing=0.1, particle_mass=0.1)
    builder.add_handle([0], kp=50.0, name="grab")
    model = builder.finalize("cpu")
    model.gravity = (0.0, 0.0, 0.0)
    sim = ws.Simulator(model, fps=100.0, substeps=1)
    live = LiveView().attach(sim)
    try:
        assert list(live.handles) == ["grab"]
        d = np.array([0.02, 0.0, -0.01])
        live.apply(sim, {("handle", 0): tuple(d)})
        sim.step_frame()
        momentum = 0.1 * sim.state.particle_qd.numpy().astype(np.float64).sum(axis=0)
        np.testing.assert_allclose(momentum, 50.0 * d * 0.01, rtol=1e-5, atol=1e-9)
    finally:
        live.close()


def test_guard_on_every_address_wants_the_pages_own_origin():
    guard = ViewGuard(1, host="0.0.0.0", port=0)
    try:
        def head(host, origin, token=guard.token):
            return (f"GET /?token={token} HTTP/1.1\r\nHost: {host}\r\nUpgrade: websocket\r\nOrigin: {origin}\r\n"
                    "\r\n").encode()

        address = f"192.0.2.7:{guard.port}"  # the machine as another computer reaches it
        assert guard.check(head(address, f"http://{address}"))[0]
        assert not guard.check(head(address, "http://evil.example"))[0]
        assert not guard.check(head(address, f"http://{address}", token="wrong"))[0]
    finally:
        guard.close()
