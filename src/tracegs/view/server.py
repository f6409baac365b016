"""``tracegs view``: a trained run in the browser (viser), rendered by our rasteriser.

The browser sends its camera; a render thread turns it into a tracegs camera (``camera.py``),
rasterises the Gaussians at the slider's time under the chosen motion model (``scene.py``) and sends
the image back as the page's background, at most ``ViewerConfig.fps`` times a second, only when the
camera, the time or a toggle changed. The dataset's cameras are frusta in the same 3D scene; clicking
one moves the view there.
"""

from __future__ import annotations

import math
import sys
import threading
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..data.cameras import Camera, focus_point
from ..run import RunError, load_run
from .camera import camera_from_view, pose_from_viewmat, vertical_fov
from .scene import MOTIONS, DatasetCameras, dataset_cameras, find_segments, phase, render_view

SPLIT_COLOURS = {"train": (31, 119, 180), "val": (255, 127, 14), "test": (44, 160, 44)}
"""Frustum colour (RGB 0-255) of each split's cameras."""


@dataclass
class ViewerConfig:
    """How the viewer renders and plays (the resolution is ``serve``'s ``width``)."""

    fps: float = 15.0
    """Most frames rendered per second for each browser; camera moves in between are coalesced."""
    play_seconds: float = 10.0
    """Time Play takes to run the slider from 0 to its end, when rendering keeps up with ``fps``."""
    slider_steps: int = 400
    """Steps of the time slider between 0 and its end."""
    jpeg_quality: int = 90
    """Quality of the JPEG images sent to the browser."""
    frustum_scale: float = 0.05
    """Size of the camera frusta, as a share of the cameras' distance to the point they look at."""
    zoom_out: float = 2.0
    """The first view looks at the point the cameras look at from this many times the first training
    camera's distance to it, so that the cameras show as frusta around the scene."""
    look_down: float = 0.5
    """... and from above that camera: the tangent of the added elevation."""


def round_step(step: float) -> float:
    """The largest of 1, 2, 5 x 10^k not above ``step`` (> 0): a slider step that reads well."""
    power = 10.0 ** math.floor(math.log10(step))
    return max(m * power for m in (1, 2, 5) if m * power <= step * (1 + 1e-9))


class Viewer:
    """A running viewer: ``url``, ``port``, ``stop()``; ``wait()`` blocks until Ctrl-C."""

    def __init__(
        self,
        server,
        run,
        cameras: DatasetCameras,
        t_end: float,
        width: int,
        config: ViewerConfig,
        simulated=None,
    ):
        self.server, self.run, self.width, self.config = server, run, width, config
        self.simulated = simulated  # the run's MuJoCo model run from the handover (``--simulator``)
        self.predictor = run.predictor.with_background(cameras.background)
        self.model = self.predictor.model
        self.t_max, self.t_end = self.predictor.t_max, t_end
        self.step = round_step(t_end / config.slider_steps)
        self.segments, segments_note = find_segments(run.path, run.model.gaussians["means"].shape[0])
        self._playing = False
        self.frames = 0
        """Frames sent to the browsers so far."""
        self._wake, self._stopped = threading.Event(), threading.Event()
        self._geometry: tuple | None = None  # ((t, motion), gaussians) of the last frame
        self._shown: dict[int, tuple] = {}  # client id -> what its last frame showed
        self._add_gui(cameras, segments_note)
        self._add_cameras(cameras)
        server.on_client_connect(self._connected)
        server.on_client_disconnect(lambda client: self._shown.pop(client.client_id, None))
        self._thread = threading.Thread(target=self._loop, name="tracegs-view", daemon=True)
        self._thread.start()

    @property
    def port(self) -> int:
        return self.server.get_port()

    @property
    def url(self) -> str:
        host = self.server.get_host()
        host = "127.0.0.1" if host in ("0.0.0.0", "") else host
        return f"http://{f'[{host}]' if ':' in host else host}:{self.port}/"

    def stop(self) -> None:
        """Stop rendering and the web server."""
        self._stopped.set()
        self._wake.set()
        self._thread.join(timeout=10)
        self.server.stop()

    def wait(self) -> None:
        """Serve until Ctrl-C (or :meth:`stop` from another thread)."""
        try:
            while not self._stopped.wait(0.5):
                pass
        except KeyboardInterrupt:
            pass
        finally:
            self.stop()

    # ----- GUI ------------------------------------------------------------------------------------
    def _add_gui(self, cameras: DatasetCameras, segments_note: str) -> None:
        gui, model = self.server.gui, self.model
        n = model.gaussians["means"].shape[0]
        gui.add_markdown(
            f"**{self.run.path.name}**: {model.method}, {n} Gaussians, trained on t <= {self.t_max:.3f}"
        )
        marks = [(0.0, "0"), (self.t_end, f"{self.t_end:.2f}")]
        if 0 < self.t_max < self.t_end:
            marks.insert(1, (self.t_max, "training end"))
        self.time = gui.add_slider(
            "time", 0.0, self.t_end, self.step, 0.0, marks=tuple(marks),
            hint=f"t <= {self.t_max:.3f}: the training span; later: predicted",
        )  # fmt: skip
        self.phase = gui.add_markdown(phase(0.0, self.t_max, "trace"))
        self.play = gui.add_button("Play", hint="run the time slider in a loop")
        has_physics = model.dynamics is not None
        choices = tuple(m for m, v in MOTIONS.items() if v != "simulator" or self.simulated is not None)
        self.motion = gui.add_dropdown(
            "motion", choices, initial_value="TRACE physics" if has_physics else "f_defo alone",
            disabled=not has_physics or model.deformation is None,
            hint="after the training end: TRACE's learned physics, or f_defo queried past its span (DefGS)",
        )  # fmt: skip
        self.paint = gui.add_checkbox(
            "segments", False, disabled=self.segments is None,
            hint=segments_note or "colour the Gaussians by their segment (tracegs segment)",
        )  # fmt: skip
        self.show_cameras = gui.add_checkbox(
            "dataset cameras", bool(cameras.cameras), disabled=not cameras.cameras
        )
        legend = ", ".join(
            f"<span style='color: rgb{SPLIT_COLOURS[s]}'>{s}</span> {len(c)}"
            for s, c in cameras.cameras.items()
            if c
        )
        gui.add_markdown(
            cameras.note or f"cameras (a frustum per pose; click one to look through it): {legend}"
        )
        self.status = gui.add_markdown("")
        for handle in (self.time, self.motion, self.paint):
            handle.on_update(self._changed)
        self.play.on_click(self._toggle_play)
        self.show_cameras.on_update(self._toggle_cameras)

    def _changed(self, _event=None) -> None:
        self.phase.content = phase(float(self.time.value), self.t_max, MOTIONS[self.motion.value])
        self._wake.set()

    def _toggle_play(self, _event=None) -> None:
        self._playing = not self._playing
        self.play.label = "Pause" if self._playing else "Play"
        self._wake.set()

    def _toggle_cameras(self, _event=None) -> None:
        for frustum in self.frusta:
            frustum.visible = bool(self.show_cameras.value)

    # ----- the dataset's cameras --------------------------------------------------------------------
    def _add_cameras(self, cameras: DatasetCameras) -> None:
        every = [cam for cams in cameras.cameras.values() for cam in cams]
        self.frusta = []
        if not every:
            self._initial_view_of_box()
            return
        viewmats = torch.stack([c.viewmat.cpu() for c in every])
        target = focus_point(viewmats)
        centres = torch.stack([c.center.cpu() for c in every])
        if target is None:
            target = centres.mean(0)
        target = target.float()
        scale = self.config.frustum_scale * float((centres - target).norm(dim=-1).median())
        up = torch.nn.functional.normalize(-viewmats[:, 1, :3].mean(0), dim=0)
        self.server.scene.set_up_direction(tuple(float(v) for v in up))
        for split, cams in cameras.cameras.items():
            for i, cam in enumerate(cams):
                wxyz, position = pose_from_viewmat(cam.viewmat)
                frustum = self.server.scene.add_camera_frustum(
                    f"/cameras/{split}/{i}", vertical_fov(cam), cam.width / cam.height, scale=scale,
                    thickness=1.5, thickness_units="screen", color=SPLIT_COLOURS.get(split, (120, 120, 120)),
                    wxyz=wxyz, position=position,
                )  # fmt: skip
                frustum.on_click(self._go_to(cam))
                self.frusta.append(frustum)
        # the first view: above the first training camera and behind it, looking at the target
        first = (cameras.cameras.get("train") or every)[0]
        away = torch.nn.functional.normalize(first.center.cpu() - target, dim=0)
        direction = torch.nn.functional.normalize(away + self.config.look_down * up, dim=0)
        distance = self.config.zoom_out * float((first.center.cpu() - target).norm())
        initial = self.server.initial_camera
        initial.position = (target + distance * direction).double().numpy()
        initial.look_at = target.double().numpy()
        initial.up = up.double().numpy()
        initial.fov = vertical_fov(first)

    def _initial_view_of_box(self) -> None:
        """Without the dataset's cameras: look at the model's box from outside it."""
        lo, hi = self.model.aabb.cpu().double().numpy()
        centre, size = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
        self.server.initial_camera.look_at = centre
        self.server.initial_camera.position = centre + size * np.array([0.8, 0.8, 0.5])

    def _go_to(self, cam: Camera):
        wxyz, position = pose_from_viewmat(cam.viewmat)

        def move(event) -> None:
            if event.client is None:
                return
            event.client.camera.position = position
            event.client.camera.wxyz = wxyz
            event.client.camera.fov = vertical_fov(cam)

        return move

    # ----- rendering ------------------------------------------------------------------------------
    def _connected(self, client) -> None:
        client.camera.on_update(lambda _camera: self._wake.set())
        self._wake.set()

    def _loop(self) -> None:
        while not self._stopped.is_set():
            self._wake.wait(timeout=0.5)
            self._wake.clear()
            if self._stopped.is_set():
                return
            started = time.perf_counter()
            if self._playing:
                self._advance()
            try:
                self._render_clients()
            except Exception as err:  # keep serving; say what failed
                self.status.content = f"render failed: {type(err).__name__}: {err}"
                traceback.print_exc(file=sys.stderr)
            self._stopped.wait(max(0.0, 1.0 / self.config.fps - (time.perf_counter() - started)))
            if self._playing:
                self._wake.set()

    def _advance(self) -> None:
        per_frame = max(1, round(self.t_end / self.step / (self.config.play_seconds * self.config.fps)))
        t = round(float(self.time.value) / self.step + per_frame) * self.step
        self.time.value = 0.0 if t > self.t_end + 1e-9 else min(t, self.t_end)

    def _render_clients(self) -> None:
        t, motion = float(self.time.value), MOTIONS[self.motion.value]
        segments = self.segments if self.paint.value else None
        for client in self.server.get_clients().values():
            cam = client.camera
            shown = (cam.update_timestamp, t, motion, segments is not None)
            if self._shown.get(client.client_id) == shown:
                continue
            width = min(self.width, max(int(cam.image_width), 8))
            camera = camera_from_view(cam.wxyz, cam.position, cam.fov, cam.aspect, width)
            image = render_view(self.predictor, self._gaussians(t, motion), camera, segments)
            client.scene.set_background_image(image, format="jpeg", jpeg_quality=self.config.jpeg_quality)
            self._shown[client.client_id] = shown
            self.frames += 1

    def _gaussians(self, t: float, motion: str) -> dict:
        if self._geometry is None or self._geometry[0] != (t, motion):
            if motion == "simulator":
                geometry = self.predictor.gaussians_carried(
                    t, self.simulated.labels, self.simulated.transforms
                )
            else:
                geometry = self.predictor.gaussians_at(t, motion)
            self._geometry = ((t, motion), geometry)
        return self._geometry[1]


def serve(
    run: str | Path,
    port: int = 8080,
    host: str = "127.0.0.1",
    data: str | Path | None = None,
    device: str = "auto",
    block: bool = True,
    t_end: float | None = None,
    width: int = 320,
    config: ViewerConfig | None = None,
    simulator: bool = False,
) -> Viewer:
    """``tracegs view``: serve the run ``run`` at ``http://host:port/`` (a free port above ``port`` when
    it is taken; ``Viewer.port`` says which) and print the URL. The time slider runs from 0 to ``t_end``
    (default: twice the training span's end), images are rendered ``width`` pixels wide, the cameras of
    the scene folder ``data`` (default: the run's) are drawn as frusta. ``block``: serve until Ctrl-C;
    else return the running viewer at once (``stop()`` ends it). ``simulator``: the run's MuJoCo model
    (``export/simulator.py``) is a third motion."""
    if not 1 <= int(port) <= 65535:
        raise RunError(f"--port {port}: not a TCP port (1-65535)")
    if not 8 <= int(width) <= 4096:
        raise RunError(f"--width {width}: the rendered image width must be 8-4096 pixels")
    loaded = load_run(run, device)
    t_max = loaded.predictor.t_max
    t_end = 2.0 * t_max if t_end is None else float(t_end)
    if not (math.isfinite(t_end) and t_end > 0):
        raise RunError(f"--t-end {t_end}: the time slider's end must be a positive number")
    loaded.predictor.check_time(t_end, "--t-end")  # the limit every command renders to
    cameras = dataset_cameras(Path(data or loaded.config.data), loaded.config.downscale)
    simulated = None
    if simulator:
        from ..export.simulator import simulated_motion

        simulated = simulated_motion(loaded, t_end, Path(data or loaded.config.data))
    import viser  # here: the other commands do not need the web server

    server = viser.ViserServer(host=host, port=int(port), label="tracegs", verbose=False)
    viewer = Viewer(server, loaded, cameras, t_end, int(width), config or ViewerConfig(), simulated)
    print(f"tracegs view: {viewer.url} (Ctrl-C stops)", flush=True)
    if block:
        viewer.wait()
    return viewer
