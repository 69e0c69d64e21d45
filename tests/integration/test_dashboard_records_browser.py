"""The dashboard's records pages in a real headless Chromium (tests/support/browser.py).

A bundle laid out as the operator writes it (its flight: a tlog written with pymavlink's
encoder, the agent's decisions and parameters; :mod:`tests.support.tlogs`) is served by
the operator's own records server (:mod:`roost_operator.records.server`) on the
loopback; ``roost dashboard --no-cluster --records-url`` reads it. The browser lists
the Mission, opens its flight and draws: altitude and speed per autopilot, flight
modes, health levels, the failover and safety-routine markers, the trajectory; what
the bundle lacks is shown. Bad requests answer JSON errors. About 10 s.
"""

from __future__ import annotations

import hashlib
import json
import urllib.error
import urllib.request
from pathlib import Path

from selenium.webdriver.common.by import By

from roost_operator.records.server import serve
from tests.support.browser import chromium, wait_for
from tests.support.dashboardproc import running_dashboard
from tests.support.tlogs import write_flight

BUNDLE = "flights_survey_1234abcd"
FLIGHT = "drone-1-20260601T120000Z"
START = 1_780_315_200.0


def lay_out_bundle(root: Path) -> None:
    bundle = root / BUNDLE
    flight_dir = f"vehicles/drone-1/{FLIGHT}"
    files = write_flight(bundle / flight_dir, START, duration_s=60)
    entries = [
        {
            "path": f"{flight_dir}/{name}",
            "name": name,
            "flightId": FLIGHT,
            "bytes": len(data),
            "sha256": hashlib.sha256(data).hexdigest(),
            **({"autopilot": name.split("/")[1].removesuffix(".json")} if "/" in name else {}),
        }
        for name, data in files.items()
    ]
    manifest = {
        "bundle": BUNDLE,
        "state": "Partial",
        "readyAt": "2026-06-01T12:02:00+00:00",
        "mission": {"namespace": "flights", "name": "survey", "phase": "Succeeded",
                    "completionTime": "2026-06-01T12:01:30+00:00"},
        "vehicles": [{"name": "drone-1", "state": "Partial", "flights": [FLIGHT]}],
        "flights": [{"flightId": FLIGHT, "vehicle": "drone-1", "state": "Complete",
                     "armedAt": "2026-06-01T12:00:00Z", "disarmedAt": "2026-06-01T12:01:00Z"}],
        "files": entries,
        "missing": [{"vehicle": "drone-1", "flightId": FLIGHT, "path": "autopilot-logs/ap-a/1.bin",
                     "reason": "Failed on the vehicle: log download cut by a reboot"}],
    }  # fmt: skip
    (bundle / "manifest.json").write_text(json.dumps(manifest))


def test_a_missions_flight_is_listed_and_plotted_from_its_bundle(tmp_path: Path) -> None:
    lay_out_bundle(tmp_path / "bundles")
    records = serve(tmp_path / "bundles", "127.0.0.1", 0)
    records_url = f"http://127.0.0.1:{records.server_address[1]}"
    try:
        with (
            running_dashboard(
                tmp_path / "dashboard.log", "--no-cluster", "--records-url", records_url
            ) as url,
            chromium(tmp_path / "chromedriver.log") as driver,
        ):
            for path, code in (
                ("api/records/nope", 404),
                (f"api/records/{BUNDLE}/plot?flight=x", 404),
            ):
                try:
                    urllib.request.urlopen(url + path, timeout=10)
                except urllib.error.HTTPError as error:
                    assert (error.code, "error" in json.loads(error.read())) == (code, True)
                else:
                    raise AssertionError(f"{path} answered 200")
            driver.get(url + "records")
            wait_for(
                driver,
                "the bundle listed",
                "return document.querySelector('#bundles tbody tr')",
                20,
            )
            driver.find_element(By.CSS_SELECTOR, f"tr[data-bundle='{BUNDLE}']").click()
            wait_for(driver, "its flight", "return document.querySelector('#flights li')", 20)
            missing = driver.find_element(By.ID, "missing").text
            assert "log download cut by a reboot" in missing
            driver.find_element(By.CSS_SELECTOR, f"li[data-flight='{FLIGHT}']").click()
            wait_for(driver, "the plot", "return window.__roostRecords.plot", 30)
            drawn = driver.execute_script(
                """
                const q = (s) => Array.from(document.querySelectorAll(s));
                return {
                  alt: q('#alt polyline').map((p) => p.dataset.autopilot),
                  speed: q('#speed polyline').length,
                  track: q('#trajectory polyline').length,
                  points: q('#alt polyline')[0].points.length,
                  modes: q('#bands text.mode').map((t) => t.dataset.mode),
                  levels: q('#bands rect.health').map((r) => r.dataset.level),
                  markers: q('#alt line.marker').map((l) => l.classList[1]),
                  listed: document.getElementById('markers').textContent,
                  title: document.getElementById('plot-title').textContent,
                };
                """
            )
    finally:
        records.shutdown()
        records.server_close()
    assert drawn["alt"] == ["ap-a", "ap-b"]
    assert drawn["speed"] == 2 and drawn["track"] == 2 and drawn["points"] == 600
    assert drawn["modes"] == ["GUIDED", "GUIDED", "LAND"]
    assert sorted(drawn["levels"]) == ["ERROR", "OK"]
    assert drawn["markers"] == ["Failover", "SafetyRoutine"]
    assert "ap-a -> ap-b: GPS lost" in drawn["listed"]
    assert FLIGHT in drawn["title"]
