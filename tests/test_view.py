"""`cogs view` on a tiny trained run: a real viser server, and the page in a real browser
(headless Chromium driven by selenium): the scene shows, the time slider moves the person,
the exact server-side image is cogs' own render; bad options and a taken port are one-line
errors; Ctrl-C stops it cleanly.

The browser test needs Debian's `chromium` and `chromium-driver` (.ci/run installs them);
without them it skips and says so, unless COGS_REQUIRE_BROWSER=1 (CI) makes that a failure.
"""

from __future__ import annotations

import io
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch

from cogs.cli import main
from tests.fixtures import TINY

viser = pytest.importorskip("viser", reason="the viewer extra is not installed (pip install -e \".[viewer]\")")

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def run(small_synthetic, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("view") / "run"
    assert main(["train", "--scene", str(small_synthetic), "--out", str(out), "--set", *TINY]) == 0
    return out


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def port_is_free(port: int) -> bool:
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
            return True
        except OSError:
            return False


# -- options ------------------------------------------------------------------------------


def test_a_port_in_use_is_refused_naming_the_option(run, capsys):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert main(["view", "--run", str(run), "--port", str(port)]) == 2
    err = capsys.readouterr().err
    assert f"--port {port}" in err and "in use" in err and "Traceback" not in err


@pytest.mark.parametrize("args, names", [
    (["--motion", "anny:run"], "--motion"),
    (["--object", "hand-right", "--hand-bone", "tail.L"], "--hand-bone"),
    (["--attach-frame", "500", "--object", "hand-left"], "--attach-frame"),
    (["--fps", "0"], "--fps"),
    (["--device", "tpu"], "--device"),
    (["--image-width", "3"], "--image-width"),
    (["--host", "192.0.2.1"], "--host"),  # TEST-NET-1: an address of no machine here
])
def test_bad_options_are_one_line_errors_before_anything_is_served(run, capsys, args, names):
    port = free_port()
    assert main(["view", "--run", str(run), "--port", str(port), *args]) == 2
    err = capsys.readouterr().err
    assert names in err and "Traceback" not in err
    assert port_is_free(port)


# -- cameras ------------------------------------------------------------------------------


def test_a_training_camera_survives_the_trip_through_the_browsers_camera(small_synthetic):
    from cogs.data.scene import load_scene
    from cogs.use.view import browser_camera, cogs_camera

    s = load_scene(small_synthetic, validate=False)
    for t in (0, s.n_frames - 1):
        vm, K = s.cameras.world_to_camera[t], s.cameras.K[t]
        wxyz, position, fov = browser_camera(vm, K, s.height)
        vm2, K2 = cogs_camera(wxyz, position, fov, s.width, s.height)
        np.testing.assert_allclose(vm2, vm, atol=1e-9)
        np.testing.assert_allclose(K2[1, 1], K[1, 1], rtol=1e-9)


# -- the server ---------------------------------------------------------------------------


def test_each_step_sends_the_human_and_object_as_cogs_poses_them_and_never_the_scene_again(run):
    from cogs.use.playback import timestep_poses
    from cogs.render.projection import covariance_3d
    from cogs.use.view import RENDERERS, View

    viewer = View(run_dir=run, port=free_port(), motion="anny:walk:0.5", object="hand-right").start()
    try:
        scene_buffer = viewer.handles["scene"].buffer.copy()
        scene_sent = viewer.handles["scene"].buffer
        k = viewer.n - 1
        viewer.slider.value = k  # as the page's slider does
        assert viewer.shown(timeout=60) == k
        assert viewer.status.content.startswith(f"frame {k} / {k}")
        frame, poses = timestep_poses(viewer.play.motion, viewer.obj, k, viewer.T)
        with torch.no_grad():
            vm = torch.as_tensor(viewer.cameras.viewmats[k], dtype=torch.float32)
            want = viewer.model.splats(frame, vm, ("human", "object"), poses)
        for name in ("human", "object"):
            h = viewer.handles[name]
            np.testing.assert_array_equal(h.centers, want[name].means.numpy())
            np.testing.assert_allclose(h.covariances, covariance_3d(want[name].quats, want[name].scales).numpy(),
                                       atol=2e-3 * float(want[name].scales.max() ** 2), rtol=2e-3)
        # Overlays: the skeleton joins the posed bone heads, the object's axes sit at its pose.
        viewer.show_skeleton.value = viewer.show_trajectory.value = True
        assert viewer.shown(timeout=60) == k
        h = viewer.model.human
        with torch.no_grad():
            _, joints = h.body.bone_transforms(*poses["human"], h.shape)
        J = joints[0].numpy()
        bones = [(p, j) for j, p in enumerate(h.body.bone_parents) if p >= 0]
        np.testing.assert_allclose(viewer.skeleton.points, np.stack([[J[p], J[j]] for p, j in bones]), atol=1e-6)
        np.testing.assert_allclose(viewer.object_axes.position, poses["object"][0].numpy(), atol=1e-6)
        # The object rides on the right wrist: it moved with the walk.
        assert float(poses["object"][0].sub(viewer.obj.translation[0]).norm()) > 0.1
        # The scene's splats went out once, when the page was built.
        assert viewer.handles["scene"].buffer is scene_sent
        np.testing.assert_array_equal(viewer.handles["scene"].buffer, scene_buffer)
        # Branch toggles and the exact renderer hide what the browser would draw.
        viewer.toggles["human"].value = False
        viewer.renderer.value = RENDERERS[1]
        assert viewer.shown(timeout=60) == k
        assert not any(h.visible for h in viewer.handles.values())
        viewer.renderer.value = RENDERERS[0]
        assert viewer.shown(timeout=60) == k
        assert not viewer.handles["human"].visible and viewer.handles["scene"].visible
    finally:
        viewer.close()


def test_play_walks_the_timeline_in_order_and_pause_stops_it(run):
    from cogs.use.view import View

    viewer = View(run_dir=run, port=free_port()).start()
    try:
        viewer.speed.value = "4"
        viewer._toggle_play()  # the Play button's callback
        assert viewer.play_button.label == "Pause"
        deadline = time.monotonic() + 120
        while len(viewer.timings) < 4:
            assert time.monotonic() < deadline, "playing never advanced"
            time.sleep(0.05)
        viewer._toggle_play()
        assert viewer.play_button.label == "Play"
        sent = [t["step"] for t in viewer.timings[:4]]
        assert sent == [1, 2, 3, 4]  # every step in order, none skipped
        k = viewer.shown(timeout=60)
        assert k is not None and viewer.slider.value == k
    finally:
        viewer.close()


def test_the_viewer_makes_no_tensor_on_an_implicit_device(run):
    """With the default device set to `meta`, a tensor made without the model's device fails
    beside the model's CPU tensors: loading, posing a new motion, sending a step, the exact
    image's camera."""
    from cogs.use.view import RENDERERS, View

    torch.set_default_device("meta")
    try:
        viewer = View(run_dir=run, port=free_port(), motion="anny:walk:0.5", object="hand-left").start()
        try:
            viewer.slider.value = 3
            assert viewer.shown(timeout=60) == 3
            viewer.renderer.value = RENDERERS[1]
            viewer.show_skeleton.value = viewer.show_trajectory.value = True
            viewer.slider.value = 4
            assert viewer.shown(timeout=60) == 4
            vm, K = viewer.cameras.viewmats[4], viewer.cameras.Ks[4]
            viewer._render_image(vm, K, 32, 24, 4)
        finally:
            viewer.close()
    finally:
        torch.set_default_device("cpu")
    assert viewer.timings and all(t["splats"] > 0 for t in viewer.timings[:1])


def _start(run: Path, port: int, *args: str, log: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    # SIGINT back to its default in the child: pytest-xdist's workers ignore it, and a child
    # inherits an ignored signal (Python then never raises KeyboardInterrupt), as would a
    # viewer started from a non-interactive shell's background job.
    proc = subprocess.Popen([sys.executable, "-m", "cogs.cli", "view", "--run", str(run), "--port", str(port), *args],
                            stdout=log.open("w"), stderr=subprocess.STDOUT, env=env, cwd=ROOT,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 180
    while True:
        assert proc.poll() is None, f"cogs view exited:\n{log.read_text()}"
        try:
            urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=5).close()
            return proc
        except OSError:
            assert time.monotonic() < deadline, f"cogs view never served:\n{log.read_text()}"
            time.sleep(0.5)


def _stop(proc: subprocess.Popen) -> int:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            return proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            raise
    return proc.returncode


def test_ctrl_c_stops_the_viewer_cleanly_and_an_open_address_is_warned_about(run, tmp_path):
    port = free_port()
    log = tmp_path / "view.log"
    proc = _start(run, port, "--host", "0.0.0.0", log=log)
    assert _stop(proc) == 0
    out = log.read_text()
    assert "exposed to the network" in out and "--host 0.0.0.0" in out
    assert "Traceback" not in out and "stopping the viewer" in out
    assert port_is_free(port)


# -- the page in a real browser -----------------------------------------------------------


def _browser() -> tuple[str, str]:
    """(chromium, chromedriver) or a skip saying what is missing."""
    pytest.importorskip("selenium", reason="selenium is not installed (pip install -e \".[viewer,dev]\")")
    chromium = next((p for p in map(shutil.which, ("chromium", "chromium-browser", "google-chrome")) if p), None)
    driver = shutil.which("chromedriver")
    if chromium is None or driver is None:
        why = ("no headless Chromium here (Debian: apt-get install chromium chromium-driver; .ci/run installs "
               f"them): chromium {chromium or 'missing'}, chromedriver {driver or 'missing'}")
        if os.environ.get("COGS_REQUIRE_BROWSER") == "1":
            pytest.fail(why)
        pytest.skip(why)
    return chromium, driver


def test_the_page_shows_the_scene_and_the_time_slider_moves_the_person(run, tmp_path):
    """Headless Chromium (software WebGL) opens `cogs view`, waits for the scene, and moves
    the time slider through the page: the canvas is not blank, and between the two steps it
    changes where cogs' own renderer puts the person (and the object) at either step, and
    nowhere else. The exact renderer then shows cogs' own image at the page's camera, and
    the camera button takes the view to the training camera of the current frame."""
    chromium, driver_path = _browser()
    from PIL import Image
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import WebDriverWait

    port = free_port()
    proc = _start(run, port, log=tmp_path / "view.log")
    opts = webdriver.ChromeOptions()
    opts.binary_location = chromium
    for a in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--use-angle=swiftshader",
              "--enable-unsafe-swiftshader", "--window-size=800,600", "--force-device-scale-factor=1"):
        opts.add_argument(a)
    browser = webdriver.Chrome(options=opts, service=Service(driver_path))
    try:
        browser.set_page_load_timeout(120)
        browser.set_script_timeout(120)
        browser.get(f"http://127.0.0.1:{port}/")
        wait = WebDriverWait(browser, 120, poll_frequency=0.25)

        def status() -> str:
            return next((line for line in browser.execute_script("return document.body.innerText").splitlines()
                         if line.startswith("frame ")), "")

        def canvas():
            # The WebGL canvas: the one with the largest drawing buffer (the page holds others).
            return max(browser.find_elements(By.TAG_NAME, "canvas"),
                       key=lambda c: int(c.get_attribute("width") or 0) * int(c.get_attribute("height") or 0))

        def shot() -> np.ndarray:
            return np.asarray(Image.open(io.BytesIO(canvas().screenshot_as_png)).convert("RGB")).astype(np.int16)

        def settled() -> np.ndarray:
            """The canvas once two screenshots half a second apart agree (the splats sorted and
            drawn); on a loaded machine software WebGL may take minutes."""
            last = shot()
            for _ in range(480):
                time.sleep(0.5)
                now = shot()
                if np.array_equal(now, last):
                    return now
                last = now
            raise AssertionError("the canvas never settled")

        def visible() -> np.ndarray:
            """[H, W] True where the page shows the canvas itself (not the panel or a notification)."""
            grid = browser.execute_script("""
                const c = arguments[0], r = c.getBoundingClientRect(), out = [];
                for (let y = r.top + 0.5; y < r.bottom; y += 4) {
                    const row = [];
                    for (let x = r.left + 0.5; x < r.right; x += 4) row.push(document.elementFromPoint(x, y) === c ? 1 : 0);
                    out.push(row);
                }
                return out;""", canvas())
            g = np.asarray(grid, bool).repeat(4, 0).repeat(4, 1)
            return g

        def set_frame(k: int) -> None:
            slider_id = browser.find_element(By.XPATH, "//label[text()='Frame']").get_attribute("for")
            box = browser.find_element(By.XPATH, f"//div[@id='{slider_id}']/following-sibling::div//input")
            box.send_keys(Keys.CONTROL, "a")
            box.send_keys(str(k), Keys.ENTER)
            wait.until(lambda _: status().startswith(f"frame {k} /"))

        def choose(label: str, option: str) -> None:
            box_id = browser.find_element(By.XPATH, f"//label[text()='{label}']").get_attribute("for")
            browser.find_element(By.ID, box_id).click()
            wait.until(lambda _: browser.find_elements(By.XPATH, f"//*[@role='option' and normalize-space()='{option}']"))
            browser.find_element(By.XPATH, f"//*[@role='option' and normalize-space()='{option}']").click()

        wait.until(lambda _: status().startswith("frame 0 /"))
        first = settled()
        H, W = first.shape[:2]
        seen = visible()[:H, :W]
        assert seen.mean() > 0.3, "the panel hides most of the canvas"
        # Not blank: many distinct colours, and far from one flat colour.
        pixels = first[seen]
        assert len(np.unique(pixels // 8, axis=0)) > 200 and pixels.std(0).mean() > 10

        last_step = int(status().split("/")[1].split()[0])
        set_frame(last_step)
        second = settled()
        changed = (np.abs(second - first).sum(-1) > 40) & seen

        # Where the person and the object are at either step, by cogs' own renderer at the
        # page's camera (the training camera of frame 0, the canvas' size).
        from cogs.model import Model
        from cogs.data.scene import load_scene
        from cogs.use.view import RENDERERS, browser_camera, cogs_camera

        model = Model.load(run)
        scene = load_scene(Path(json_scene(run)), validate=False)
        vm0, K0 = scene.cameras.world_to_camera[0], scene.cameras.K[0]
        wxyz, position, fov = browser_camera(vm0, K0, scene.height)
        vm, K = cogs_camera(wxyz, position, fov, W, H)
        region = np.zeros((H, W), bool)
        with torch.no_grad():
            for frame in (0, last_step):
                r = model.render(torch.as_tensor(vm, dtype=torch.float32), torch.as_tensor(K, dtype=torch.float32), W, H,
                                 frame, branches=("human", "object", "scene"))
                for b in ("human", "object"):
                    region |= r.branch_alpha[b][..., 0].numpy() > 0.02
        region = _dilate(region, 8)
        moved, outside = int((changed & region).sum()), int((changed & ~region).sum())
        assert moved > 0.2 * (region & seen).sum(), f"the person did not move on the page ({moved} px changed)"
        assert outside < 0.02 * changed.sum() + 50, f"the page changed away from the person ({outside} px)"

        # The exact renderer: cogs' own image of the last step at the page's camera, behind the scene.
        choose("Renderer", RENDERERS[1])
        wait.until(lambda _: "exact image" in status())
        exact = settled()
        seen &= visible()[:H, :W]  # the status line grew
        with torch.no_grad():
            want = model.render(torch.as_tensor(vm, dtype=torch.float32), torch.as_tensor(K, dtype=torch.float32), W, H,
                                last_step).rgb.clamp(0, 1).numpy() * 255
        err_exact = np.abs(exact - want)[seen].mean()
        err_splats = np.abs(second - want)[seen].mean()
        assert err_exact < 5 and err_exact < 0.5 * err_splats, (err_exact, err_splats)  # 0..255 per channel

        # "Go to the training camera": the view jumps to the last step's training camera.
        browser.find_element(By.XPATH, "//button[contains(., 'Go to the training camera')]").click()
        wait.until(lambda _: np.abs(shot() - exact)[seen].mean() > 5)
        jumped = settled()
        seen &= visible()[:H, :W]
        wxyz, position, fov = browser_camera(scene.cameras.world_to_camera[last_step], scene.cameras.K[last_step],
                                             scene.height)
        vm15, K15 = cogs_camera(wxyz, position, fov, W, H)
        with torch.no_grad():
            want = model.render(torch.as_tensor(vm15, dtype=torch.float32), torch.as_tensor(K15, dtype=torch.float32), W,
                                H, last_step).rgb.clamp(0, 1).numpy() * 255
        err_jump = np.abs(jumped - want)[seen].mean()
        assert err_jump < 5, err_jump
        Image.fromarray(np.concatenate([first, second, exact, jumped], 1).astype(np.uint8)).save(tmp_path / "steps.png")
    finally:
        browser.quit()
        assert _stop(proc) == 0


def json_scene(run: Path) -> str:
    import json

    return json.loads((run / "run.json").read_text())["scene"]


def _dilate(mask: np.ndarray, r: int) -> np.ndarray:
    from scipy.ndimage import binary_dilation

    return binary_dilation(mask, iterations=r)


def test_ctrl_c_while_the_scene_is_still_being_sent_stops_the_server_and_exits_cleanly(run, monkeypatch):
    """The server answers before the scene is sent: a Ctrl-C in between (a user quick on the
    keys, or the test above when the host is slow) stops it and exits 0, not 130 with the
    port left open."""
    from cogs.use.view import View, Viewer

    def interrupted(self):
        raise KeyboardInterrupt

    monkeypatch.setattr(Viewer, "_build_scene", interrupted)
    port = free_port()
    assert View(run_dir=run, port=port).run() == 0
    deadline = time.monotonic() + 10
    while not port_is_free(port):
        assert time.monotonic() < deadline, f"port {port} still held after the interrupted start"
        time.sleep(0.2)
