"""Headless Chromium through Selenium for tests of what a user sees in a browser.

The ``chromium`` fixture (tests/conftest.py) wraps :func:`chromium_driver`; the helpers
below ask the page whether its images and videos loaded and save screenshots.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
WIDTH = 1400


def chromium_driver() -> Iterator[Any]:
    """Yield a headless Chromium WebDriver 1400 px wide; skip without Chromium or Selenium."""
    missing = [str(p) for p in (CHROMIUM, CHROMEDRIVER) if not p.is_file()]
    if missing:
        pytest.skip(f"headless browser tests need {' and '.join(missing)} (apt install chromium "
                    "chromium-driver)")  # fmt: skip
    webdriver = pytest.importorskip("selenium.webdriver", reason="browser tests need selenium")
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = str(CHROMIUM)
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                f"--window-size={WIDTH},1000", "--mute-audio"):  # fmt: skip
        opts.add_argument(arg)
    driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=opts)
    try:
        yield driver
    finally:
        driver.quit()


def video_state(driver: Any, selector: str = "video", timeout: float = 20.0) -> dict[str, Any]:
    """Wait until the first ``selector`` video can show a frame (readyState >= 2) or fails.

    Returns:
        ``{"readyState", "videoWidth", "videoHeight", "error"}`` of the element (error: the
        MediaError message, or None).
    """
    script = (
        "const v = document.querySelector(arguments[0]);"
        "if (!v) return null;"
        "return {readyState: v.readyState, videoWidth: v.videoWidth,"
        " videoHeight: v.videoHeight, error: v.error ? (v.error.message || v.error.code) : null};"
    )
    end = time.monotonic() + timeout
    while True:
        state = driver.execute_script(script, selector)
        if state is None:
            raise AssertionError(f"the page has no element {selector!r}")
        if state["readyState"] >= 2 or state["error"] or time.monotonic() > end:
            return dict(state)
        time.sleep(0.1)


def broken_images(driver: Any) -> list[str]:
    """The ``src`` of every ``<img>`` of the page that did not load (naturalWidth 0)."""
    return list(
        driver.execute_script(
            "return Array.from(document.images)"
            ".filter(i => !(i.complete && i.naturalWidth > 0)).map(i => i.src);"
        )
    )


def video_page(video: Path) -> Path:
    """Write ``<video>.html`` next to ``video``: a page showing only that video."""
    page = video.with_suffix(".html")
    page.write_text(f'<!DOCTYPE html><html><body><video controls src="{video.name}"></video>'
                    "</body></html>")  # fmt: skip
    return page


def screenshot(driver: Any, path: Path, width: int = WIDTH) -> Path:
    """Save a screenshot of the whole page, ``width`` pixels wide, to ``path``."""
    height = int(driver.execute_script("return document.documentElement.scrollHeight"))
    driver.set_window_size(width, min(max(height, 600), 16000))
    driver.save_screenshot(str(path))
    return path
