"""``roost dashboard`` in a real browser, on the sandbox's live fleet.

Everything is real: ``roost sandbox up`` (control plane, operator, one agent per vehicle
streaming its telemetry, simulated autopilots over UDP, the dashboard it starts), a
headless Chromium driven over WebDriver, and the user's clicks. The test

1. waits until the page shows every vehicle airborne with live telemetry;
2. breaks drone-1's active autopilot with ``roost fault`` and measures, in the page, when
   the vehicle turns red and when the timeline shows the failover (printed; only a
   generous timeout is asserted);
3. aborts the Mission through the confirmation dialog, checks the dialog listed every
   target, and waits until the page shows every vehicle landed;
4. e-stops one vehicle through its dialog and reads the agent's acknowledgement.

Screenshots go to the test's directory (and to ``$ROOST_DASHBOARD_SCREENSHOTS`` when
set: docs/dashboard.png is one of them).
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from selenium import webdriver
from selenium.webdriver.common.by import By

from tests.support.browser import chromium, wait_for
from tests.support.sandbox import RunningSandbox, await_running, running_sandbox

# serial: the sandbox's simulated autopilots and agents run in real time against a 200 ms
# silence limit; on two busy cores a stall of both autopilots of a vehicle lands it (the
# agent rightly finds no healthy standby), so `make e2e` runs these after the rest,
# beside at most one other serial file (Makefile, E2E_SERIAL).
pytestmark = [
    pytest.mark.cluster,
    pytest.mark.slow,
    pytest.mark.serial,
    pytest.mark.timeout(600),
]

VEHICLES = ("drone-1", "drone-2")
FAULT_VEHICLE = "drone-1"
STEP_TIMEOUT_S = 90.0
SHOWS_FAILOVER_TIMEOUT_S = 30.0  # generous: the figure is measured and printed, not asserted

# Installed in the page: the wall-clock time at which the DOM first showed each thing.
WATCH_FAILOVER = """
const vehicle = arguments[0];
window.__seen = {};
const check = () => {
  const row = document.querySelector(`#fleet tr[data-vehicle="${vehicle}"]`);
  if (!window.__seen.red && row && ["ERROR", "STALE"].includes(row.dataset.worst)) {
    window.__seen.red = Date.now();
    const shown = window.__roost.doc.vehicles.find((v) => v.name === vehicle);
    window.__seen.sampled = shown && shown.sampledAt * 1000;
  }
  const item = [...document.querySelectorAll('#timeline li[data-kind="failover"]')]
    .find((li) => li.dataset.object.endsWith(`/${vehicle}`));
  if (!window.__seen.timeline && item) window.__seen.timeline = Date.now();
};
new MutationObserver(check).observe(document.body,
  {subtree: true, childList: true, attributes: true, characterData: true});
check();
"""


@pytest.fixture
def sandbox(tmp_path: Path) -> Iterator[RunningSandbox]:
    args = ["--vehicles", str(len(VEHICLES)), "--no-live", "--no-fault", "--dashboard-port", "0"]
    with running_sandbox(tmp_path, args) as running:
        yield running


def screenshot(driver: webdriver.Chrome, directory: Path, name: str) -> Path:
    path = directory / f"{name}.png"
    assert driver.save_screenshot(str(path)), f"no screenshot {path}"
    wanted = os.environ.get("ROOST_DASHBOARD_SCREENSHOTS")
    if wanted:
        Path(wanted).mkdir(parents=True, exist_ok=True)
        shutil.copy(path, Path(wanted) / path.name)
    return path


def rows(driver: webdriver.Chrome) -> dict[str, dict[str, Any]]:
    found: dict[str, dict[str, Any]] = driver.execute_script(
        """return Object.fromEntries([...document.querySelectorAll('#fleet tbody tr')]
             .map((tr) => [tr.dataset.vehicle, {...tr.dataset,
                 alt: tr.cells[5].textContent, mission: tr.cells[6].textContent}]));"""
    )
    return found


def confirm(driver: webdriver.Chrome, button_css: str) -> list[str]:
    """Click ``button_css``, read the dialog's targets, confirm; the targets listed."""
    driver.find_element(By.CSS_SELECTOR, button_css).click()
    wait_for(driver, "the confirmation dialog", "return document.getElementById('confirm').open", 5)
    targets = [li.text for li in driver.find_elements(By.CSS_SELECTOR, "#confirm-targets li")]
    driver.find_element(By.ID, "confirm-ok").click()
    return targets


def test_dashboard_shows_a_failover_and_aborts_the_mission(
    sandbox: RunningSandbox, tmp_path: Path
) -> None:
    recorded = await_running(sandbox)
    assert recorded.dashboard is not None
    with chromium(tmp_path / "chromedriver.log") as driver:
        driver.get(recorded.dashboard)

        def airborne() -> bool:
            shown = rows(driver)
            return all(
                v in shown
                and shown[v]["telemetry"] == "live"
                and shown[v]["worst"] == "OK"
                and shown[v]["landed"] == "false"
                for v in VEHICLES
            )

        deadline = time.monotonic() + STEP_TIMEOUT_S + 60
        while not airborne():
            assert time.monotonic() < deadline, f"not airborne in the page: {rows(driver)}"
            time.sleep(0.2)
        markers = driver.find_elements(By.CSS_SELECTOR, "#markers g.marker")
        assert sorted(m.get_attribute("data-vehicle") for m in markers) == list(VEHICLES)
        screenshot(driver, tmp_path, "dashboard-flying")

        # 2. A fault: the vehicle turns red, the timeline shows the failover.
        driver.execute_script(WATCH_FAILOVER, FAULT_VEHICLE)
        injected_ms = time.time() * 1000
        fault = sandbox.roost("fault", FAULT_VEHICLE, "px4-a", "silence")
        assert "faults now silence" in fault.stdout
        seen = wait_for(
            driver,
            "the vehicle red and the failover in the timeline",
            "return window.__seen.red && window.__seen.timeline && window.__seen",
            SHOWS_FAILOVER_TIMEOUT_S,
        )
        red_ms, timeline_ms = seen["red"] - injected_ms, seen["timeline"] - injected_ms
        print(f"\nfault injected -> vehicle red in the page: {red_ms:.0f} ms")
        print(f"fault injected -> failover in the timeline: {timeline_ms:.0f} ms")
        if seen.get("sampled"):
            shown_ms = seen["red"] - seen["sampled"]
            print(f"agent sample with the failover -> red in the DOM: {shown_ms:.0f} ms")
        row = rows(driver)[FAULT_VEHICLE]
        wait_for(
            driver,
            "px4-b active in the fleet table",
            f"return document.querySelector('#fleet tr[data-vehicle=\"{FAULT_VEHICLE}\"]')"
            ".dataset.active === 'px4-b'",
            10,
        )
        assert driver.find_element(
            By.CSS_SELECTOR, f'#markers g[data-vehicle="{FAULT_VEHICLE}"]'
        ).get_attribute("data-worst") in ("ERROR", "STALE"), row
        # The Kubernetes Event of the same failover follows (watched, Roost Events only).
        wait_for(
            driver,
            "the failover Event in the timeline",
            "return [...document.querySelectorAll("
            '\'#timeline li[data-source="event"][data-kind="failover"]\')]'
            f".some((li) => li.dataset.object === 'RedundantAutopilot/{FAULT_VEHICLE}')",
            STEP_TIMEOUT_S,
        )
        screenshot(driver, tmp_path, "dashboard")

        # 3. Abort the mission through the dialog: every vehicle lands.
        targets = confirm(driver, 'button.abort[data-mission="default/survey"]')
        assert targets == ["default/survey", *VEHICLES]
        wait_for(
            driver,
            "the abort to be accepted",
            "return window.__roost.lastAction && window.__roost.lastAction",
            30,
        )
        outcome = driver.execute_script("return window.__roost.lastAction")
        assert outcome["ok"], outcome
        assert sandbox.get("mission", "survey", "default")["spec"]["abort"] is True
        deadline = time.monotonic() + STEP_TIMEOUT_S
        while not all(rows(driver)[v]["landed"] == "true" for v in VEHICLES):
            assert time.monotonic() < deadline, f"not all landed in the page: {rows(driver)}"
            time.sleep(0.2)
        wait_for(
            driver,
            "the mission panel to show the abort",
            "const m = document.querySelector('.mission[data-mission=\"default/survey\"]');"
            "return m && ['Aborting', 'Aborted'].includes(m.dataset.phase)",
            STEP_TIMEOUT_S,
        )
        assert driver.find_elements(
            By.CSS_SELECTOR, '#timeline li[data-source="event"][data-kind="safety"]'
        ), "no safety-routine Event in the timeline"
        screenshot(driver, tmp_path, "dashboard-aborted")

        # 4. E-stop one vehicle through its dialog; the agent acknowledges. Once the abort
        # is over: while it runs, the operator's own commands would supersede ours.
        wait_for(
            driver,
            "the mission to be Aborted",
            "return document.querySelector('.mission[data-mission=\"default/survey\"]')"
            ".dataset.phase === 'Aborted'",
            STEP_TIMEOUT_S,
        )
        driver.execute_script("window.__roost.lastAction = null")
        targets = confirm(driver, 'button.estop[data-vehicle="drone-2"]')
        assert targets == ["drone-2"]
        outcome = wait_for(
            driver,
            "the e-stop acknowledgement",
            "return window.__roost.lastAction && window.__roost.lastAction",
            30,
        )
        assert outcome["ok"] and outcome["answer"]["executed"], outcome
        assert [a["result"] for a in outcome["answer"]["acknowledgements"]] == ["Executed"]
        latencies = driver.execute_script("return window.__roost.latencies")
        assert latencies, "the page measured no sample"
        latencies.sort()
        print(
            f"agent sample -> DOM: p50 {latencies[len(latencies) // 2]:.0f} ms, "
            f"max {latencies[-1]:.0f} ms over {len(latencies)} samples"
        )
