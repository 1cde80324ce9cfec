"""Headless Debian chromium for the viewer tests (through its chromedriver and selenium), and image comparison."""

from __future__ import annotations

import io
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

#: software WebGL (no GPU here), no sandbox (CI runs as root)
CHROMIUM_ARGS = ("--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                 "--disable-dev-shm-usage", "--window-size=800,600")


#: chromium raises its browser and GPU processes to nice -8 when it can (root can): on a shared machine the wrapper
#: starts it at nice 10 without CAP_SYS_NICE, so none of its processes can take CPU from other work
NICE_WRAPPER = """#!/bin/sh
exec setpriv --inh-caps=-sys_nice --bounding-set=-sys_nice nice -n 10 {browser} "$@"
"""


def launch_headless_chromium():
    """A selenium Chrome driver on Debian's chromium (niced, see ``NICE_WRAPPER``); RuntimeError with the reason
    (what is missing, how to get it) when it cannot start."""
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError as exc:
        raise RuntimeError("selenium is not installed (pip install 'kc-splatfacto[browser-test]')") from exc
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    if browser is None or driver is None:
        raise RuntimeError("no chromium/chromedriver on PATH: apt-get install chromium chromium-driver")
    options = webdriver.ChromeOptions()
    options.binary_location = browser
    if shutil.which("setpriv") and shutil.which("nice"):
        wrapper = Path(tempfile.mkdtemp(prefix="kc-chromium-")) / "chromium"
        wrapper.write_text(NICE_WRAPPER.format(browser=browser))
        wrapper.chmod(0o755)
        options.binary_location = str(wrapper)
    for arg in CHROMIUM_ARGS:
        options.add_argument(arg)
    return webdriver.Chrome(options=options, service=Service(driver))


def headless_chromium():
    """:func:`launch_headless_chromium`, or skip the test with its reason."""
    try:
        return launch_headless_chromium()
    except RuntimeError as exc:
        pytest.skip(str(exc))


def screenshot(driver) -> np.ndarray:
    """[H, W, 3] float64 RGB in [0, 1] of the page as shown."""
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(driver.get_screenshot_as_png())).convert("RGB"), dtype=np.float64) / 255.0


def resize(image: np.ndarray, width: int, height: int) -> np.ndarray:
    from PIL import Image

    pil = Image.fromarray((np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8))
    return np.asarray(pil.resize((width, height), Image.BILINEAR), dtype=np.float64) / 255.0


def correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation of two same-shaped images' pixel values."""
    a, b = a.reshape(-1) - a.mean(), b.reshape(-1) - b.mean()
    return float((a @ b) / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-12))


def wait_for(condition: Callable[[], bool], timeout: float, poll: float = 0.5) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(poll)
    return condition()
