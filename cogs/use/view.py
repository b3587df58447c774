"""`cogs view`: a trained run in the browser, on a timeline (viser, the `viewer` extra).

    cogs view --run RUN                                   # then open http://127.0.0.1:8080
    cogs view --run RUN --motion anny:walk --object hand-right --port 8090

The static scene's splats are sent once; the human and the object are re-posed and sent at
each step of the timeline (`--motion` and `--object` as in `cogs render`, so a new motion
plays here too). The page's panel holds:

* Timeline: the "Frame" slider and its number box, Play / Pause, the speed, and a status
  line "frame K / N" that appears once step K has been sent (scripts can type a step into
  the box and wait for that line, as tests/test_view.py does);
* Show: one toggle per branch (human, object, scene), and overlays of the body skeleton
  and of the object's trajectory with its current pose;
* Camera: jump to the training camera of the current frame (a page opens at the first
  step's; without the run's scene, a circle round the person stands in for them);
* Renderer: viser's splatting in the browser (fast, approximate: its own sorting and
  blending), or an image from cogs' own rasterizer rendered on the server at the
  browser's camera (exact: what the metrics measure), shown behind the overlays.

It binds 127.0.0.1 unless `--host` says otherwise; any other address is warned about, as it
exposes the reconstruction to whoever can reach the machine. Ctrl-C stops it.
"""

from __future__ import annotations

import ipaddress
import logging
import socket
import threading
import time
from dataclasses import dataclass

import numpy as np
import torch

from cogs.errors import UserError
from cogs.use.playback import PlaybackOptions

log = logging.getLogger("cogs")

RENDERERS = ("splats in the browser (viser)", "cogs rasterizer on the server (exact)")
SPEEDS = ("0.25", "0.5", "1", "2", "4")
BRANCH_NAMES = ("human", "object", "scene")


@dataclass(kw_only=True)
class View(PlaybackOptions):
    """Show a trained run in the browser: the static scene, the human and the object on a
    timeline (any motion and object path, as `cogs render`), branch toggles, overlays, and
    cogs' own exact rasterizer on demand."""

    host: str = "127.0.0.1"
    """Address to serve on. 127.0.0.1 (the default) is this machine only; 0.0.0.0 exposes
    the viewer to the network."""
    port: int = 8080
    """Port to serve on (an error if it is taken)."""
    image_width: int = 640
    """Width in pixels of the server-side image (cogs' rasterizer); its height follows the
    browser's aspect."""

    def run(self) -> int:
        try:
            viewer = self.start()
        except KeyboardInterrupt:  # Ctrl-C while it was still loading or sending the scene
            log.info("stopping the viewer")
            return 0
        try:
            log.info("cogs view: open http://%s:%d (%d steps at %g fps; Ctrl-C stops)",
                     _url_host(self.host), viewer.port, viewer.n, viewer.play.fps)
            viewer.wait()
        except KeyboardInterrupt:
            log.info("stopping the viewer")
        finally:
            viewer.close()
        return 0

    def start(self) -> "Viewer":
        """Check every option, load the run, resolve the motion and object path, and serve
        (in background threads) until `Viewer.close()`."""
        device = self.check_playback_options()
        if not 16 <= self.image_width <= 4096:
            raise UserError(f"--image-width {self.image_width}: must be in 16..4096")
        try:
            import viser  # noqa: F401
        except ImportError:
            raise UserError("cogs view needs the viewer extra (viser): pip install -e \".[viewer]\"") from None
        check_address(self.host, self.port)

        from cogs.use.objects import object_path
        from cogs.use.playback import find_scene, load_model, load_playback

        model = load_model(self, device)
        scene = find_scene(self.run_dir, self.scene)
        play = load_playback(self, model, scene, want_object="object" in model.available())
        with torch.no_grad():
            obj = object_path(play.object, model, play.motion, play.attach_frame, self.hand_bone) \
                if play.motion is not None or play.object == "none" else None
        return Viewer(play, obj, self.host, self.port, self.image_width)


# -- the address ------------------------------------------------------------------------


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _url_host(host: str) -> str:
    return f"[{host}]" if ":" in host else host


def check_address(host: str, port: int) -> None:
    """--host and --port, before any work: the port must be free there (viser itself would
    quietly move to the next one). Warns when the address is not this machine's loopback."""
    if not 1 <= port <= 65535:
        raise UserError(f"--port {port}: must be in 1..65535")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as e:
        raise UserError(f"--host {host}: not an address of this machine ({e.strerror})") from None
    family, _, _, _, addr = infos[0]
    with socket.socket(family, socket.SOCK_STREAM) as s:
        # As the server will bind (asyncio sets SO_REUSEADDR): a port in TIME_WAIT is free.
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(addr)
        except OSError as e:
            if e.errno == 98:  # EADDRINUSE
                raise UserError(f"--port {port}: already in use on {host} (another viewer?); choose another "
                                "--port") from None
            raise UserError(f"--host {host} --port {port}: cannot serve there ({e.strerror})") from None
    if not _is_loopback(host):
        log.warning("--host %s: the viewer is exposed to the network: anyone who can reach this machine "
                    "on port %d can see the reconstruction. Use --host 127.0.0.1 to keep it local.", host, port)


# -- cameras between cogs (world_to_camera, K) and the browser --------------------------


def browser_camera(viewmat: np.ndarray, K: np.ndarray, height: int) -> tuple[np.ndarray, np.ndarray, float]:
    """A camera in the scene format's convention (world_to_camera [4, 4], OpenCV; K [3, 3]
    of an image `height` pixels tall) as viser's: (wxyz of camera->world [4], position [3],
    vertical field of view in radians). viser's camera axes are OpenCV's too."""
    from cogs.geometry.rotations import rotmat_to_quat

    R = np.asarray(viewmat, np.float64)[:3, :3]
    t = np.asarray(viewmat, np.float64)[:3, 3]
    wxyz = rotmat_to_quat(torch.from_numpy(R.T.copy())).numpy()
    fov = 2.0 * np.arctan(0.5 * height / K[1, 1])
    return wxyz, -R.T @ t, float(fov)


def cogs_camera(wxyz, position, fov: float, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """viser's camera (camera->world wxyz and position, vertical fov in radians) seen as an
    image of width x height pixels: (world_to_camera [4, 4], K [3, 3]), centred principal
    point, square pixels."""
    from cogs.geometry.rotations import quat_to_rotmat

    R = quat_to_rotmat(torch.as_tensor(np.asarray(wxyz, np.float64), device="cpu")).numpy()  # camera -> world
    vm = np.eye(4)
    vm[:3, :3] = R.T
    vm[:3, 3] = -R.T @ np.asarray(position, np.float64)
    f = 0.5 * height / np.tan(0.5 * fov)
    K = np.array([[f, 0.0, 0.5 * width], [0.0, f, 0.5 * height], [0.0, 0.0, 1.0]])
    return vm, K


# -- the viewer -------------------------------------------------------------------------


class Viewer:
    """A viser server showing one run's playback. Everything that touches the model runs on
    one worker thread; the GUI's callbacks only record what is wanted and wake it."""

    def __init__(self, play, obj, host: str, port: int, image_width: int = 640):
        import viser

        from cogs.use.cameras import camera_path
        from cogs.use.playback import timestep_poses

        self.play, self.obj, self.model = play, obj, play.model
        self.image_width = image_width
        model, motion = play.model, play.motion
        self.T = model.n_frames
        self.n = len(motion) if motion is not None else max(self.T, 1)
        self.have = tuple(b for b in model.available() if b != "object" or obj is not None)
        self.dev = model.device
        with torch.no_grad():
            self.prepared = model.prepare(tuple(b for b in self.have if b == "human"))
        self._poses = lambda k: timestep_poses(motion, obj, k, self.T)
        # Cameras per step: the training camera of the clip frame the step shows, or a
        # circle round the person when the scene cannot be found.
        if play.scene is not None:
            self.cameras = camera_path("train", self.n, play.scene, model, motion, play.up, None, play.fps)
            self.camera_name = "training camera"
        else:
            self.cameras = camera_path("orbit", self.n, None, model, motion, play.up, None, play.fps)
            self.camera_name = "orbit camera"  # no scene found: a circle round the person

        logging.getLogger("websockets").setLevel(logging.WARNING)  # one line per connection otherwise
        self.server = viser.ViserServer(host=host, port=port, label="cogs", verbose=False)
        self.port = self.server.get_port()
        if self.port != port:  # taken between the check and the bind
            self.server.stop()
            raise UserError(f"--port {port}: already in use on {host}; choose another --port")
        try:  # the server already answers: whatever stops the set-up below also stops it
            self._set_up(play)
        except BaseException:
            self.server.stop()
            raise

    def _set_up(self, play) -> None:
        """The scene, the controls, the first camera and the worker threads, once serving."""
        self.server.scene.set_up_direction(tuple(float(x) for x in play.up))
        self._cond = threading.Condition()
        self._stop = False
        self._want, self._shown = 0, None  # the step asked for, the step last sent
        self._restyle = False  # a toggle or the renderer changed: send the step again
        self._busy = False
        self._dirty_clients: set[int] = set()  # clients whose exact image is out of date
        self._playing = False
        self.timings: list[dict] = []  # per step sent: re-posing, queueing for the browser (ms)
        self._build_scene()
        self._build_gui()
        self._set_initial_camera(0)
        self.server.on_client_connect(self._on_connect)
        self._worker = threading.Thread(target=self._work, name="cogs-view-worker", daemon=True)
        self._player = threading.Thread(target=self._play_loop, name="cogs-view-player", daemon=True)
        self._worker.start()
        self._player.start()

    # -- scene ------------------------------------------------------------------------
    def _splats(self, names: tuple[str, ...], k: int):
        frame, poses = self._poses(k)
        vm = torch.as_tensor(self.cameras.viewmats[k], dtype=torch.float32, device=self.dev)
        return self.model.splats(frame, vm, names, poses, self.prepared)

    @staticmethod
    def _arrays(s) -> dict[str, np.ndarray]:
        from cogs.render.projection import covariance_3d

        return {"centers": s.means.detach().cpu().numpy(),
                "covariances": covariance_3d(s.quats, s.scales).detach().cpu().numpy(),
                "rgbs": s.rgb.clamp(0.0, 1.0).detach().cpu().numpy(),
                "opacities": s.opacities[:, None].detach().cpu().numpy()}

    @torch.no_grad()
    def _build_scene(self) -> None:
        sc = self.server.scene
        self.handles = {}
        for name, s in self._splats(self.have, 0).items():
            # The scene is static: these are its only splats ever sent (colours seen from
            # the first step's camera where it has view-dependent colour).
            self.handles[name] = sc.add_gaussian_splats(f"/{name}", **self._arrays(s))
        self._shown = 0
        h = self.model.human
        self.skeleton = None
        if h is not None and self.play.motion is not None:
            self._bones = [(p, j) for j, p in enumerate(h.body.bone_parents) if p >= 0]
            self.skeleton = sc.add_line_segments("/overlays/skeleton", self._skeleton_points(0), (255, 64, 32),
                                                 thickness=2.0, thickness_units="screen", visible=False)
        self.trajectory = self.object_axes = None
        if self.obj is not None:
            p = self.obj.translation.detach().cpu().numpy()
            seg = np.stack([p[:-1], p[1:]], 1) if len(p) > 1 else np.repeat(p[:, None], 2, 1)
            self.trajectory = sc.add_line_segments("/overlays/trajectory", seg, (32, 160, 255), thickness=2.0,
                                                   thickness_units="screen", visible=False)
            self.object_axes = sc.add_frame("/overlays/object_pose", axes_length=0.15, axes_radius=0.006,
                                            visible=False, **self._object_pose(0))

    def _joints(self, k: int) -> np.ndarray:
        """[J, 3] the body's joints (bone heads, world) at step k."""
        h, m = self.model.human, self.play.motion
        with torch.no_grad():
            _, joints = h.body.bone_transforms(m.pose[k : k + 1], m.transl[k : k + 1], h.shape)
        return joints[0].detach().cpu().double().numpy()

    def _skeleton_points(self, k: int) -> np.ndarray:
        J = self._joints(k)
        return np.stack([[J[p], J[j]] for p, j in self._bones]).astype(np.float32)

    def _object_pose(self, k: int) -> dict:
        return {"wxyz": self.obj.quat[k].detach().cpu().numpy().astype(np.float64),
                "position": self.obj.translation[k].detach().cpu().numpy().astype(np.float64)}

    # -- GUI --------------------------------------------------------------------------
    def _build_gui(self) -> None:
        gui = self.server.gui
        with gui.add_folder("Timeline"):
            self.slider = gui.add_slider("Frame", min=0, max=max(self.n - 1, 1), step=1, initial_value=0,
                                         disabled=self.n < 2)
            self.play_button = gui.add_button("Play", disabled=self.n < 2)
            self.speed = gui.add_dropdown("Speed", SPEEDS, initial_value="1")
            self.status = gui.add_markdown(self._status_text(0, None))
        with gui.add_folder("Show"):
            self.toggles = {b: gui.add_checkbox(b.capitalize(), initial_value=True, disabled=b not in self.have)
                            for b in BRANCH_NAMES}
            self.show_skeleton = gui.add_checkbox("Skeleton", initial_value=False, disabled=self.skeleton is None)
            self.show_trajectory = gui.add_checkbox("Object trajectory", initial_value=False,
                                                    disabled=self.trajectory is None)
        with gui.add_folder("Camera"):
            self.jump = gui.add_button(f"Go to the {self.camera_name}")
        self.renderer = gui.add_dropdown("Renderer", RENDERERS, initial_value=RENDERERS[0])

        self.slider.on_update(lambda _: self._request(int(self.slider.value)))
        self.play_button.on_click(lambda _: self._toggle_play())
        for box in self.toggles.values():
            box.on_update(lambda _: self._restyled())
        self.show_skeleton.on_update(lambda _: self._overlays())
        self.show_trajectory.on_update(lambda _: self._overlays())
        self.jump.on_click(lambda event: self._jump(event.client))
        self.renderer.on_update(lambda _: self._on_renderer())

    def _status_text(self, k: int, ms: float | None) -> str:
        """The status line; "frame K / N" leads it once step K has been sent (scripts and the
        browser test wait for it)."""
        m = self.play.motion
        clip = f" · clip frame {self._poses(k)[0]}" if m is not None and m.clip_time is not None else ""
        took = f" · {ms:.0f} ms" if ms is not None else ""
        return f"frame {k} / {self.n - 1}{clip}{took}"

    def _request(self, k: int) -> None:
        with self._cond:
            self._want = min(max(k, 0), self.n - 1)
            self._cond.notify_all()

    def _toggle_play(self) -> None:
        with self._cond:
            self._playing = not self._playing
            self._cond.notify_all()
        self.play_button.label = "Pause" if self._playing else "Play"

    def _restyled(self) -> None:
        with self._cond:
            self._restyle = True  # re-pose what became visible; redraw the server image
            self._dirty_clients.update(self.server.get_clients())
            self._cond.notify_all()

    def _exact(self) -> bool:
        return self.renderer.value == RENDERERS[1]

    def _on_renderer(self) -> None:
        if not self._exact():
            for c in self.server.get_clients().values():
                c.scene.set_background_image(None)
        self._restyled()

    def _overlays(self) -> None:
        if self.skeleton is not None:
            self.skeleton.visible = bool(self.show_skeleton.value)
        if self.trajectory is not None:
            self.trajectory.visible = self.object_axes.visible = bool(self.show_trajectory.value)
        self._restyled()  # the skeleton is only posed while shown

    # -- cameras ----------------------------------------------------------------------
    def _camera(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Step k's camera for viser: (wxyz, position, the point it orbits, vertical fov).
        The orbit point lies on the optical axis at the depth of the body's root."""
        vm, K = self.cameras.viewmats[k], self.cameras.Ks[k]
        wxyz, pos, fov = browser_camera(vm, K, self.cameras.height)
        depth = 2.0
        if self.play.motion is not None and self.model.human is not None:
            root = self._joints(k)[0]
            depth = max(float((vm[:3, :3] @ root + vm[:3, 3])[2]), 0.5)
        return wxyz, pos, pos + depth * vm[2, :3], fov

    def _set_initial_camera(self, k: int) -> None:
        _, pos, look, fov = self._camera(k)
        cam = self.server.initial_camera
        cam.position, cam.look_at, cam.up, cam.fov = pos, look, self.play.up, fov

    def _jump(self, client) -> None:
        if client is None:
            return
        with self._cond:
            k = self._want
        wxyz, pos, look, fov = self._camera(k)
        with client.atomic():
            client.camera.fov = fov
            client.camera.position = pos
            client.camera.wxyz = wxyz  # keeps the camera's roll: the orbit's up follows it
            client.camera.look_at = look

    def _on_connect(self, client) -> None:
        client.camera.on_update(lambda cam: self._camera_moved(cam.client.client_id))
        self._camera_moved(client.client_id)

    def _camera_moved(self, client_id: int) -> None:
        if self._exact():
            with self._cond:
                self._dirty_clients.add(client_id)
                self._cond.notify_all()

    # -- work -------------------------------------------------------------------------
    def _work(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._stop or self._want != self._shown or self._restyle or
                                    (self._dirty_clients and self._exact()))
                if self._stop:
                    return
                k, repose = self._want, self._want != self._shown or self._restyle
                dirty, self._dirty_clients = self._dirty_clients, set()
                self._restyle, self._busy = False, True
            try:
                if repose:
                    self._show(k)
                    dirty = set(self.server.get_clients())
                if self._exact():
                    for cid in dirty:
                        self._render_for(cid, k)
            except Exception:  # a bug: keep serving, and say so
                log.exception("cogs view: step %d failed", k)
            with self._cond:
                self._shown, self._busy = k, False
                self._cond.notify_all()

    @torch.no_grad()
    def _show(self, k: int) -> None:
        """Re-pose the moving branches at step k and send them (the scene never moves)."""
        t0 = time.perf_counter()
        exact = self._exact()
        moving = tuple(b for b in ("human", "object") if b in self.have and self.toggles[b].value and not exact)
        arrays = {name: self._arrays(s) for name, s in self._splats(moving, k).items()} if moving else {}
        t1 = time.perf_counter()
        with self.server.atomic():
            for name, handle in self.handles.items():
                if name in arrays:
                    handle.set_gaussians(**arrays[name])
                handle.visible = bool(self.toggles[name].value) and not exact
            if self.skeleton is not None and self.skeleton.visible:
                self.skeleton.points = self._skeleton_points(k)
            if self.object_axes is not None:
                pose = self._object_pose(k)
                self.object_axes.wxyz, self.object_axes.position = pose["wxyz"], pose["position"]
            ms = 1000 * (time.perf_counter() - t0)
            self.status.content = self._status_text(k, ms)
        self.server.flush()
        self.timings.append({"step": k, "pose_ms": 1000 * (t1 - t0), "queue_ms": 1000 * (time.perf_counter() - t1),
                             "splats": sum(len(a["centers"]) for a in arrays.values())})

    @torch.no_grad()
    def _render_for(self, client_id: int, k: int) -> None:
        """cogs' own render of step k at a client's camera, behind the overlays."""
        client = self.server.get_clients().get(client_id)
        if client is None:
            return
        cam = client.camera
        if cam.image_width <= 0 or cam.image_height <= 0:
            return
        t0 = time.perf_counter()
        W = self.image_width
        H = max(16, int(round(W * cam.image_height / cam.image_width)))
        vm, K = cogs_camera(cam.wxyz, cam.position, cam.fov, W, H)
        img, depth = self._render_image(vm, K, W, H, k)
        if not self._exact():  # switched back to the splats while this rendered
            return
        client.scene.set_background_image(img, format="jpeg", depth=depth)
        client.flush()
        took = time.perf_counter() - t0
        self.status.content = f"{self._status_text(k, None)} · exact image {W}x{H} in {took:.1f} s"

    @torch.no_grad()
    def _render_image(self, vm: np.ndarray, K: np.ndarray, W: int, H: int, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Step k by cogs' rasterizer, the visible branches only: (RGB uint8 [H, W, 3], camera
        depth [H, W] in metres, far where nothing opaque was hit)."""
        names = tuple(b for b in self.have if self.toggles[b].value)
        frame, poses = self._poses(k)
        bg = torch.zeros(3, dtype=torch.float32, device=self.dev)
        r = self.model.render(torch.as_tensor(vm, dtype=torch.float32, device=self.dev),
                              torch.as_tensor(K, dtype=torch.float32, device=self.dev), W, H, frame,
                              branches=names, background=bg, poses=poses, prepared=self.prepared)
        img = (r.rgb.clamp(0, 1).cpu().numpy() * 255).round().astype(np.uint8)
        depth = r.depth.where(r.alpha > 0.5, torch.full_like(r.depth, 1e3))[..., 0].cpu().numpy()
        return img, depth

    def _play_loop(self) -> None:
        """Advance the slider at the chosen speed, never faster than steps are sent."""
        last = time.perf_counter()
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._stop or self._playing)
                if self._stop:
                    return
                self._cond.wait_for(lambda: self._stop or self._shown == self._want or not self._playing)
                if self._stop:
                    return
                if not self._playing:
                    continue
                k = (self._want + 1) % self.n
            period = 1.0 / (self.play.fps * float(self.speed.value))
            time.sleep(max(0.0, last + period - time.perf_counter()))
            last = time.perf_counter()
            if self._playing:
                self.slider.value = k  # its callback requests the step

    # -- lifetime ---------------------------------------------------------------------
    def wait(self) -> None:
        """Serve until interrupted."""
        while True:
            time.sleep(3600)

    def shown(self, timeout: float | None = None) -> int | None:
        """Wait until the wanted step, and every change since, has been sent; returns the
        step (None on timeout)."""
        with self._cond:
            ok = self._cond.wait_for(lambda: self._shown == self._want and not (self._busy or self._restyle or
                                                                                (self._dirty_clients and self._exact())), timeout)
            return self._shown if ok else None

    def close(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        for t in (self._worker, self._player):
            t.join(timeout=5.0)
        self.server.stop()
