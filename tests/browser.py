"""The browser for viewer tests: headless chromium with software WebGL through selenium, a free port, waiting, and
page screenshots kept as artefacts (``$NARF_TEST_ARTEFACTS``, default ``test-artefacts/``)."""

from __future__ import annotations

import os
import shutil
import socket
import time
from pathlib import Path

import numpy as np

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")
MISSING = "chromium and chromium-driver are not installed (apt-get install chromium chromium-driver)"
ARTEFACTS = Path(os.environ.get("NARF_TEST_ARTEFACTS", Path(__file__).resolve().parents[1] / "test-artefacts"))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait(condition, seconds: float, what: str):
    """Poll ``condition`` until it returns something other than None / False; fail after ``seconds``."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        value = condition()
        if value is not None and value is not False:
            return value
        time.sleep(0.1)
    raise AssertionError(f"timed out after {seconds:g} s waiting for {what}")


def chromium():
    """A headless chromium (1000 x 700) with software WebGL: the test machines have no GPU."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    for flag in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=1000,700"):
        options.add_argument(flag)
    options.add_argument("--use-angle=swiftshader")
    options.add_argument("--enable-unsafe-swiftshader")
    options.binary_location = CHROMIUM
    return webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)


def page_pixels(driver, name: str) -> np.ndarray:
    """The page as an RGB array, its left 60 % (away from the control panel); saved as ``viewer-<name>.png``."""
    import cv2

    ARTEFACTS.mkdir(parents=True, exist_ok=True)
    png = driver.get_screenshot_as_png()
    (ARTEFACTS / f"viewer-{name}.png").write_bytes(png)
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    return image[:, : int(image.shape[1] * 0.6)].astype(np.float64)
