"""A real headless Chromium driven through WebDriver (selenium), for the dashboard tests.

Debian's ``chromium`` and ``chromium-driver`` (``make test`` installs them with
docker/debian-packages.sh); nothing is downloaded at run time: the driver and browser are
given by path, so selenium's own manager never looks for them. Without them the tests
that need a browser skip and say what to install.
"""

from __future__ import annotations

import contextlib
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from selenium import webdriver
from selenium.webdriver.chrome.service import Service

from tests.support.waiting import wait_until

WINDOW = (1400, 900)


def binaries() -> tuple[str, str] | None:
    """(browser, driver) paths, or None when Debian's packages are not installed."""
    browser = shutil.which("chromium")
    driver = shutil.which("chromedriver")
    return (browser, driver) if browser and driver else None


@contextlib.contextmanager
def chromium(log: Path) -> Iterator[webdriver.Chrome]:
    """A headless Chromium driven over WebDriver; the driver's log goes to ``log``."""
    found = binaries()
    if found is None:
        pytest.skip("needs Debian's chromium and chromium-driver (apt-get install them)")
    browser, driver_path = found
    options = webdriver.ChromeOptions()
    options.binary_location = browser
    for arg in (
        "--headless=new",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-dev-shm-usage",
        f"--window-size={WINDOW[0]},{WINDOW[1]}",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
    ):
        options.add_argument(arg)
    service = Service(executable_path=driver_path, log_output=str(log))
    driver = webdriver.Chrome(service=service, options=options)
    try:
        yield driver
    finally:
        driver.quit()


def wait_for(
    driver: webdriver.Chrome,
    what: str,
    script: str,
    timeout_s: float,
    *args: Any,
    poll_s: float = 0.05,
) -> Any:
    """Run ``script`` (JavaScript returning a value) until it is truthy; that value."""
    return wait_until(
        what,
        lambda: driver.execute_script(script, *args),
        timeout_s,
        poll_s,
        explain=lambda: (
            "page: "
            + str(
                driver.execute_script("return window.__roost && JSON.stringify(window.__roost.doc)")
            )
        ),
    )
