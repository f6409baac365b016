"""A screenshot of `tracegs view` in a headless Chromium (Debian's `chromium` package), for the README.

    .venv/bin/python scripts/viewer_screenshot.py --run runs/fan --data data/fan --out docs/figures/viewer.png

Starts the viewer on the run with its time slider at ``--time`` (a predicted time by default), opens
the page in Chromium through its DevTools protocol, waits until the viewer has sent the browser its
rendered frames and the page is still, closes the page's notifications (headless Chromium draws WebGL
in software, which viser points out) and writes the screenshot as a palette PNG. Without ``--run``,
trains a tiny run on a generated scene first (a smoke test of the script).
"""

from __future__ import annotations

import argparse
import base64
import io
import itertools
import json
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

from PIL import Image
from websockets.sync.client import connect

CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
    "--window-size=1280,800",
]
CLOSE_NOTIFICATIONS = "document.querySelectorAll('.mantine-Notification-closeButton').forEach(b => b.click())"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def tiny_run(root: Path) -> tuple[Path, Path]:
    """A run trained with ``--preset tiny`` on the tests' generated scene."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from tests.conftest import write_tiny_scene

    from tracegs.config import make_config
    from tracegs.train.trainer import Trainer

    scene = write_tiny_scene(root / "scene", size=64)
    cfg = make_config("tiny", data=scene, run=root / "run", device="cpu")
    Trainer(cfg, progress=False).train()
    return root / "run", scene


class DevTools:
    """The DevTools protocol of one Chromium page: ``call(method, **params)`` -> result."""

    def __init__(self, port: int, deadline: float):
        while True:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=2) as answer:
                    pages = [t for t in json.load(answer) if t["type"] == "page"]
                if pages:
                    break
            except OSError:
                pass
            if time.monotonic() > deadline:
                raise TimeoutError("chromium's DevTools did not answer")
            time.sleep(0.2)
        self.socket = connect(pages[0]["webSocketDebuggerUrl"], max_size=None)
        self.ids = itertools.count(1)

    def call(self, method: str, **params) -> dict:
        call_id = next(self.ids)
        self.socket.send(json.dumps({"id": call_id, "method": method, "params": params}))
        while True:
            message = json.loads(self.socket.recv())
            if message.get("id") == call_id:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                return message["result"]


def wait_for_frames(viewer, settle: float, deadline: float) -> None:
    """Until the viewer has sent a frame and sent none for ``settle`` seconds."""
    last, since = -1, time.monotonic()
    while time.monotonic() < deadline:
        if viewer.frames != last:
            last, since = viewer.frames, time.monotonic()
        elif last > 0 and time.monotonic() - since > settle:
            return
        time.sleep(0.1)
    raise TimeoutError(f"the viewer sent {viewer.frames} frames before the deadline")


def screenshot(viewer, browser: str, timeout: float = 120.0) -> Image.Image:
    """Chromium's screenshot (1280 x 800) of the viewer's page once its frames have arrived."""
    deadline = time.monotonic() + timeout
    port = free_port()
    with tempfile.TemporaryDirectory() as profile:
        flags = CHROMIUM_FLAGS + [f"--user-data-dir={profile}", f"--remote-debugging-port={port}"]
        process = subprocess.Popen(
            [browser, *flags, "about:blank"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        try:
            page = DevTools(port, deadline)
            page.call(
                "Emulation.setDeviceMetricsOverride",
                width=1280,
                height=800,
                deviceScaleFactor=1,
                mobile=False,
            )
            page.call("Page.navigate", url=viewer.url)
            wait_for_frames(viewer, settle=2.0, deadline=deadline)
            page.call("Runtime.evaluate", expression=CLOSE_NOTIFICATIONS)
            time.sleep(1.0)  # the page draws the last frame and the closed notifications go
            data = page.call("Page.captureScreenshot", format="png")["data"]
            page.socket.close()
        finally:
            process.terminate()
            process.wait(timeout=10)
    return Image.open(io.BytesIO(base64.b64decode(data))).convert("RGB")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", type=Path, help="a trained run (default: train a tiny one)")
    parser.add_argument("--data", type=Path, help="its scene folder (default: the run's)")
    parser.add_argument("--out", type=Path, default=Path("docs/figures/viewer.png"))
    parser.add_argument("--time", type=float, default=None, help="slider time (default: 1.5 x t_max)")
    parser.add_argument("--segments", action="store_true", help="paint the segments (if the run has them)")
    parser.add_argument("--width", type=int, default=640, help="rendered image width")
    args = parser.parse_args()
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        sys.exit("no chromium on PATH (Debian: apt-get install chromium)")

    from tracegs.view import serve

    with tempfile.TemporaryDirectory() as tmp:
        run, data = (args.run, args.data) if args.run else tiny_run(Path(tmp))
        viewer = serve(run, port=free_port(), data=data, block=False, width=args.width)
        try:
            t = 1.5 * viewer.t_max if args.time is None else args.time
            viewer.time.value = viewer.step * round(t / viewer.step)
            if args.segments and viewer.segments is not None:
                viewer.paint.value = True
            image = screenshot(viewer, browser)
        finally:
            viewer.stop()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    image.quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(args.out, optimize=True)
    print(f"{args.out}: {args.out.stat().st_size // 1024} kB")


if __name__ == "__main__":
    main()
