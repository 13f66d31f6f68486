"""Screenshots of the viewer's page in headless Chromium (selenium), for tests and the README image.

``python -m suture_gym.viewer.browser`` (the README's image, ``docs/media/viewer.png``) runs the scripted expert on
WoundClosure in a :class:`~suture_gym.viewer.app.ViewerApp` on a free port of 127.0.0.1, pauses it during the
second stitch, opens the page in headless Chromium and saves a screenshot as a palette PNG. Needs selenium and
Pillow (the ``dev`` extra) and Debian's ``chromium`` and ``chromium-driver`` (or any Chromium and matching
chromedriver on ``PATH``); :func:`find_chromium` says what is missing. Chromium renders WebGL in software
(SwiftShader) here: no GPU or display is needed.
"""

from __future__ import annotations

import argparse
import io
import shutil
import time
from pathlib import Path

import numpy as np

#: Browser and driver executables looked for on ``PATH``, in order.
BROWSERS = ("chromium", "chromium-browser", "google-chrome")
DRIVERS = ("chromedriver",)
#: CSS hiding viser's notifications (the "software WebGL" warning would cover part of the scene).
HIDE_NOTIFICATIONS = ".mantine-Notifications-root { display: none !important; }"


def find_chromium() -> tuple[str, str]:
    """``(browser, chromedriver)`` executable paths; RuntimeError naming what is missing and how to install it."""
    browser = next((p for p in map(shutil.which, BROWSERS) if p), None)
    driver = next((p for p in map(shutil.which, DRIVERS) if p), None)
    missing = [name for name, path in (("a Chromium browser", browser), ("chromedriver", driver)) if path is None]
    if missing:
        raise RuntimeError(f"no {' and no '.join(missing)} on PATH (Debian: apt-get install chromium "
                           "chromium-driver)")
    return browser, driver


class Browser:
    """A headless Chromium window of ``width`` x ``height`` px driven by selenium (a context manager).

    Raises:
        ImportError: selenium is not installed (``pip install selenium``, in the ``dev`` extra).
        RuntimeError: no Chromium or chromedriver (:func:`find_chromium`).
    """

    def __init__(self, width: int = 1100, height: int = 700) -> None:
        try:
            from selenium import webdriver
            from selenium.webdriver.chrome.service import Service
        except ImportError as err:
            raise ImportError("browser screenshots need selenium: pip install selenium (the 'dev' extra)") from err
        browser, driver = find_chromium()
        options = webdriver.ChromeOptions()
        options.binary_location = browser
        for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", f"--window-size={width},{height}",
                    "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"):
            options.add_argument(arg)
        self.driver = webdriver.Chrome(service=Service(driver), options=options)

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def open(self, url: str) -> None:
        """Load ``url`` and hide viser's notifications."""
        self.driver.get(url)
        self.driver.execute_script(
            "const s = document.createElement('style'); s.textContent = arguments[0]; document.head.appendChild(s);",
            HIDE_NOTIFICATIONS)

    def screenshot(self) -> np.ndarray:
        """``(H, W, 3) uint8`` RGB image of the window."""
        from PIL import Image

        png = self.driver.get_screenshot_as_png()
        return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))

    def wait_for(self, ready, timeout: float = 60.0, interval: float = 0.5) -> np.ndarray:
        """Screenshots every ``interval`` s until ``ready(image)`` is true; returns that image (TimeoutError with
        the last image's size otherwise)."""
        deadline = time.monotonic() + timeout
        while True:
            image = self.screenshot()
            if ready(image):
                return image
            if time.monotonic() > deadline:
                raise TimeoutError(f"the page did not get ready in {timeout} s (last screenshot {image.shape})")
            time.sleep(interval)

    def close(self) -> None:
        self.driver.quit()


#: Width of viser's GUI panel on the right of the page, px (at the default zoom).
PANEL_PX = 360


def scene_view(image: np.ndarray) -> np.ndarray:
    """The part of a screenshot (H, W, 3) left of viser's GUI panel: the 3D view."""
    return image[:, : max(1, image.shape[1] - PANEL_PX)]


def scene_pixels(image: np.ndarray) -> int:
    """Pixels of the 3D view (:func:`scene_view`) that are not the page's white background."""
    return int(np.count_nonzero(scene_view(image).min(axis=-1) < 235))


def changed_pixels(a: np.ndarray, b: np.ndarray, threshold: int = 24) -> int:
    """Pixels of the 3D view whose colour differs by more than ``threshold`` (sum over RGB, 0-255 each) between two
    screenshots of the same size."""
    diff = np.abs(scene_view(a).astype(np.int16) - scene_view(b).astype(np.int16)).sum(axis=-1)
    return int(np.count_nonzero(diff > threshold))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m suture_gym.viewer.browser", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="SutureGym/WoundClosure-v3")
    parser.add_argument("--policy", default="expert")
    parser.add_argument("--steps", type=int, default=1300, help="env steps before the screenshot")
    parser.add_argument("--width", type=int, default=1100, help="window width, px")
    parser.add_argument("--height", type=int, default=900, help="window height, px (the page is a little less)")
    parser.add_argument("--colors", type=int, default=256, help="palette size of the PNG (at most 256)")
    parser.add_argument("--out", default="docs/media/viewer.png")
    args = parser.parse_args(argv)
    from PIL import Image

    from suture_gym.viewer.app import ViewerApp

    app = ViewerApp(args.env, policy=args.policy, port=0, speed=None)
    try:
        app.run(max_steps=args.steps)
        app.set_paused(True)
        with Browser(args.width, args.height) as browser:
            browser.open(app.view.url)
            browser.wait_for(lambda im: scene_pixels(im) > 5000)
            time.sleep(2.0)  # the panels' last updates
            image = browser.screenshot()
    finally:
        app.close()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).quantize(colors=args.colors, method=Image.Quantize.FASTOCTREE).save(args.out, optimize=True)
    print(f"{args.out}: {image.shape[1]}x{image.shape[0]} px, {scene_pixels(image)} scene pixels")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
