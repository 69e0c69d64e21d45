"""``roost dashboard`` as a process against a real API server: its guards, over HTTP.

The browser test (tests/e2e/test_dashboard_browser.py) clicks through the happy paths on
a flying sandbox; this one checks what a browser never shows, with plain HTTP and
WebSocket clients: the page's token is required to act, a confirmation that lists other
targets than the cluster has is refused (409) and writes nothing, a read-only dashboard
refuses every action, and the fleet document follows objects created after it started
(watches). No operator and no agents run here: the objects are written as a user would.
"""

from __future__ import annotations

import copy
import json
import re
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from websockets.exceptions import InvalidStatus, WebSocketException
from websockets.sync.client import connect

from roost_cli.sandbox import plan
from roost_kube.client import Kube
from roost_kube.resources import MISSIONS, REDUNDANT_AUTOPILOTS
from roost_localcluster.cluster import Cluster
from tests.support.dashboardproc import running_dashboard
from tests.support.waiting import unique, wait_until

pytestmark = pytest.mark.cluster


@contextmanager
def dashboard(cluster: Cluster, log: Path, *args: str) -> Iterator[str]:
    """A running ``roost dashboard`` on the session cluster; its URL."""
    with running_dashboard(log, "--kubeconfig", str(cluster.kubeconfig), *args) as url:
        yield url


def token_of(url: str) -> str:
    with urllib.request.urlopen(url, timeout=5) as response:
        page = response.read().decode()
    found = re.search(r'token: "([^"]*)"', page)
    assert found is not None, page
    return found.group(1)


def post(url: str, body: dict[str, Any], token: str | None) -> tuple[int, dict[str, Any]]:
    headers = {"Content-Type": "application/json"}
    if token is not None:
        headers["X-Roost-Token"] = token
    request = urllib.request.Request(
        url, data=json.dumps(body).encode(), headers=headers, method="POST"
    )
    try:
        with urllib.request.urlopen(request, timeout=20) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as error:
        return error.code, json.loads(error.read())


def document(url: str, until: Any, timeout: float = 15) -> dict[str, Any]:
    """The first fleet document the dashboard pushes that satisfies ``until``."""
    ws_url = url.replace("http://", "ws://") + "ws"
    deadline = time.monotonic() + timeout
    with connect(ws_url, open_timeout=5) as ws:
        while time.monotonic() < deadline:
            doc: dict[str, Any] = json.loads(ws.recv(timeout=deadline - time.monotonic()))
            if until(doc):
                return doc
    pytest.fail("no matching document")


def test_actions_need_the_token_and_the_exact_targets(
    roost_crds: Cluster, kube: Kube, tmp_path: Path
) -> None:
    mission = plan.mission_manifest(1)
    mission["metadata"]["name"] = name = unique("dash-mission")
    mission["spec"]["vehicles"]["selector"] = {"matchLabels": {"dashboard-test": name}}
    [vehicle] = plan.plan_fleet(1)
    autopilot = copy.deepcopy(
        plan.autopilot_manifest(
            vehicle, {a.name: "udpout://127.0.0.1:9" for a in vehicle.autopilots}
        )
    )
    autopilot["metadata"]["name"] = autopilot["spec"]["vehicleName"] = ra = unique("dash-ra")
    with dashboard(roost_crds, tmp_path / "dashboard.log") as url:
        token = token_of(url)
        assert token
        kube.apply(mission)
        kube.apply(autopilot)
        try:
            doc = document(
                url, lambda d: any(m["name"] == f"default/{name}" for m in d["missions"])
            )
            assert doc["readOnly"] is False and doc["clusterError"] is None

            abort = {"mission": f"default/{name}", "confirmed": [f"default/{name}"]}
            assert post(url + "api/abort", abort, None)[0] == 403
            assert post(url + "api/abort", abort, "not-the-token")[0] == 403
            status, answer = post(
                url + "api/abort", {**abort, "confirmed": [f"default/{name}", "drone-9"]}, token
            )
            assert status == 409 and "confirm again" in answer["error"]
            assert not kube.get(MISSIONS, name, "default")["spec"].get("abort")

            estop = {"vehicles": [ra], "confirmed": []}
            status, answer = post(url + "api/estop", estop, token)
            assert status == 409, answer
            assert "command" not in kube.get(REDUNDANT_AUTOPILOTS, ra)["spec"]

            status, answer = post(url + "api/abort", abort, token)
            assert status == 200, answer
            assert answer["mission"] == f"default/{name}" and answer["vehicles"] == []
            assert kube.get(MISSIONS, name, "default")["spec"]["abort"] is True
        finally:
            kube.delete(MISSIONS, name, "default")
            kube.delete(REDUNDANT_AUTOPILOTS, ra)


def test_read_only_refuses_every_action_and_other_origins(
    roost_crds: Cluster, tmp_path: Path
) -> None:
    with dashboard(roost_crds, tmp_path / "dashboard.log", "--read-only") as url:
        assert token_of(url) == ""
        status, answer = post(url + "api/estop", {"all": True, "confirmed": []}, "")
        assert status == 403 and "read-only" in answer["error"]
        assert document(url, lambda d: True)["readOnly"] is True
        ws_url = url.replace("http://", "ws://") + "ws"
        with (
            pytest.raises((InvalidStatus, WebSocketException)),
            connect(ws_url, origin="http://evil.example", open_timeout=5) as ws,  # type: ignore[arg-type]
        ):
            ws.recv(timeout=5)


FENCED_ORIGIN = (47.3977, 8.5456)


def test_the_arena_draws_a_missions_fence_in_a_real_browser(
    roost_crds: Cluster, kube: Kube, tmp_path: Path
) -> None:
    """A real headless Chromium (tests.support.browser) on the dashboard: a Mission's
    polygon fence appears in the arena, placed in metres from the dashboard's origin."""
    from selenium.webdriver.common.by import By  # noqa: PLC0415 - only this test drives a browser

    from tests.support.browser import chromium  # noqa: PLC0415

    lat, lon = FENCED_ORIGIN
    mission = plan.mission_manifest(1)
    mission["metadata"]["name"] = name = unique("dash-fence")
    mission["spec"]["vehicles"]["selector"] = {"matchLabels": {"dashboard-test": name}}
    d = 0.0009  # about 100 m north, 68 m east
    mission["spec"]["fence"] = {
        "polygon": [
            {"latitude": lat, "longitude": lon},
            {"latitude": lat, "longitude": lon + d},
            {"latitude": lat + d, "longitude": lon + d},
            {"latitude": lat + d, "longitude": lon},
        ],
        "maxAltitudeM": 30,
        "action": "Land",
    }
    origin = f"{lat},{lon}"
    with dashboard(roost_crds, tmp_path / "dashboard.log", "--origin", origin) as url:
        kube.apply(mission)
        try:
            with chromium(tmp_path / "chromedriver.log") as driver:
                driver.get(url)
                selector = f'#fences g[data-mission="default/{name}"]'

                def drawn() -> Any:
                    found = driver.find_elements(By.CSS_SELECTOR, f"{selector} polygon")
                    return found[0] if found else None

                polygon = wait_until("the fence in the arena", drawn, 30, 0.2)
                points = [
                    tuple(float(v) for v in p.split(","))
                    for p in polygon.get_attribute("points").split()
                ]
                # x east, y south (north up): the first vertex at the origin, the third
                # about 100 m north and 68 m east of it.
                assert points[0] == (0.0, 0.0)
                assert points[2][0] == pytest.approx(67.8, abs=1) and points[2][1] == pytest.approx(
                    -100.1, abs=1
                )
                group = driver.find_element(By.CSS_SELECTOR, selector)
                assert group.get_attribute("data-action") == "Land"
                assert "fence ≤30 m, Land" in group.text
                driver.save_screenshot(str(tmp_path / "fence.png"))
        finally:
            kube.delete(MISSIONS, name, "default")
