"""The agent's bridge drivers: the simulated bridge, and the GPIO bridge's one-hot lines."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from roost_agent.bridge import BridgeError, GpioBridge, SimulatedBridge


def test_simulated_bridge_records_selections_and_tells_listeners() -> None:
    bridge = SimulatedBridge([0, 1], initial=0)
    heard: list[int] = []
    bridge.add_listener(heard.append)
    bridge.select(1)
    assert bridge.selected == 1 and [s.channel for s in bridge.history] == [0, 1]
    assert heard == [0, 1]  # the current channel first, then every switch
    assert bridge.history[0].at <= bridge.history[1].at
    with pytest.raises(BridgeError):
        bridge.select(7)
    assert bridge.selected == 1


def test_gpio_bridge_reports_a_missing_chip_clearly(tmp_path: Path) -> None:
    with pytest.raises(BridgeError, match="cannot request GPIO lines"):
        GpioBridge(str(tmp_path / "gpiochip9"), [0, 1], 0)
    with pytest.raises(BridgeError, match="initial channel"):
        GpioBridge(str(tmp_path / "gpiochip9"), [0, 1], 5)


GPIO_SIM = Path("/sys/kernel/config/gpio-sim")


@contextlib.contextmanager
def gpio_sim_chip(lines: int) -> Iterator[tuple[str, Path]]:
    """A simulated GPIO chip from the kernel's gpio-sim module (configfs)."""
    device = GPIO_SIM / f"roost-test-{os.getpid()}"
    bank = device / "bank0"
    bank.mkdir(parents=True)
    try:
        (bank / "num_lines").write_text(str(lines))
        (device / "live").write_text("1")
        chip = (bank / "chip_name").read_text().strip()
        dev_name = (device / "dev_name").read_text().strip()
        yield f"/dev/{chip}", Path(f"/sys/devices/platform/{dev_name}/{chip}")
    finally:
        (device / "live").write_text("0")
        bank.rmdir()
        device.rmdir()


@pytest.mark.skipif(
    not GPIO_SIM.is_dir() or os.geteuid() != 0,
    reason="needs the kernel's gpio-sim module (configfs /sys/kernel/config/gpio-sim) and "
    "root; this machine's kernel has no GPIO character devices at all, so the GPIO driver "
    "is exercised here only up to requesting the lines",
)
def test_gpio_bridge_drives_one_hot_lines_on_a_simulated_chip() -> None:
    with gpio_sim_chip(4) as (chip, sysfs):

        def levels() -> list[int]:
            return [int((sysfs / f"sim_gpio{i}" / "value").read_text()) for i in range(3)]

        bridge = GpioBridge(chip, [0, 1, 2], 1)
        try:
            assert levels() == [0, 1, 0]  # the initial channel is asserted at request time
            bridge.select(2)
            assert levels() == [0, 0, 1] and bridge.selected == 2
        finally:
            bridge.close()
        low = GpioBridge(chip, [0, 1, 2], 0, active_low=True)
        try:
            assert levels() == [0, 1, 1]
        finally:
            low.close()
