"""Render a Rerun recording (.rrd) to a PNG with the Rerun viewer itself, headless.

    .venv/bin/python tools/screenshot.py demo-output/mavest.rrd docs/demo.png [--size 1600x1000]

The viewer shipped in the rerun-sdk wheel draws the recording with its stored
default layout (mavest's blueprint) through Vulkan; on a machine without a GPU
or display, Mesa's software rasteriser (Debian: ``apt-get install
mesa-vulkan-drivers``) does the drawing. The recording is checked with
``rerun rrd verify`` first: the viewer would otherwise happily screenshot its
own "failed to load" page.
"""

from __future__ import annotations

import argparse
import glob
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from mavest.service.process import free_port
from mavest.viz.viewer import rerun_binary


class ScreenshotError(Exception):
    """Why no picture could be made, in one line."""


def software_vulkan_available() -> bool:
    """Whether a Vulkan driver (e.g. Mesa's lavapipe) is installed."""
    return bool(glob.glob("/usr/share/vulkan/icd.d/*.json"))


def render(rrd: Path, png: Path, size: str = "1600x1000", timeout: float = 120.0) -> Path:
    binary = rerun_binary()
    if binary is None:
        raise ScreenshotError("the rerun viewer executable was not found (pip install rerun-sdk)")
    if not software_vulkan_available():
        raise ScreenshotError(
            "no Vulkan driver: install one, e.g. apt-get install mesa-vulkan-drivers"
        )
    verify = subprocess.run(
        [binary, "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=timeout
    )
    if verify.returncode != 0 or "1 file verified" not in verify.stderr:
        raise ScreenshotError(f"{rrd} is not a valid recording: {verify.stderr.strip()}")
    png.parent.mkdir(parents=True, exist_ok=True)
    png.unlink(missing_ok=True)
    port = free_port()
    with tempfile.TemporaryDirectory() as runtime:
        environment = {
            **os.environ,
            "RUST_LOG": "error",  # no notification pop-ups over the picture
            "XDG_RUNTIME_DIR": runtime,
            "XDG_CONFIG_HOME": runtime,  # no analytics or saved state of a previous session
        }
        viewer = subprocess.Popen(
            [
                binary,
                "--headless",
                "--renderer",
                "vulkan",
                "--bind",
                "127.0.0.1",
                "--port",
                str(port),
                "--window-size",
                size,
                "--hide-welcome-screen",
            ],
            env=environment,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            _screenshot(f"rerun+http://127.0.0.1:{port}/proxy", rrd, png, timeout)
        finally:
            viewer.terminate()
            viewer.wait(10)
    if not png.exists():
        raise ScreenshotError("the viewer made no picture")
    return png


def _screenshot(url: str, rrd: Path, png: Path, timeout: float) -> None:
    """Open the recording in the running viewer, wait until it is loaded and drawn with
    its data (plots fit their axes on the frames after the data arrives), then shoot."""
    from rerun.experimental import ViewerClient

    deadline = time.monotonic() + timeout
    while True:
        try:
            client = ViewerClient.connect(url)
            client.get_state()
            break
        except Exception as error:  # not listening yet
            if time.monotonic() > deadline:
                raise ScreenshotError(f"the headless viewer did not start: {error}") from None
            time.sleep(0.2)
    client.open(str(rrd.resolve()))
    while client.get_state().loading:
        if time.monotonic() > deadline:
            raise ScreenshotError(f"the viewer did not finish loading {rrd}")
        time.sleep(0.2)
    time.sleep(2.0)
    client.save_screenshot(str(png.resolve()))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("rrd", type=Path)
    parser.add_argument("png", type=Path)
    parser.add_argument("--size", default="1600x1000", help="window size in points (PNG is 2×)")
    args = parser.parse_args()
    try:
        print(render(args.rrd, args.png, args.size))
    except (ScreenshotError, subprocess.TimeoutExpired) as error:
        print(f"screenshot: {error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
