"""The bridge: the switch that connects exactly one autopilot's outputs to the ESCs.

In the thesis the bridge is a set of solid-state relays driven by one signal from the
companion computer. Roost drives it through the Linux GPIO character device (one output
line per autopilot, ``AutopilotSpec.bridge_channel`` = line offset, one-hot), or through
a simulated bridge that records every selection for tests and sandboxes.

``select`` is on the failover's critical path, so it does nothing but the write: the
GPIO driver precomputes the value pattern of every channel and sets all lines with a
single ``set_values`` call (one GPIO_V2_LINE_SET_VALUES ioctl, so the lines change
together as far as the kernel interface allows; whether the relays break before they
make is the circuit's business). Lines are requested with the initial pattern already
applied, so a restarted agent re-asserts the persisted active channel without ever
glitching back to the primary.
"""

from __future__ import annotations

import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any


class BridgeError(RuntimeError):
    """The bridge could not be opened or switched."""


class Bridge(ABC):
    """Connects one autopilot (by channel) to the motors."""

    @abstractmethod
    def select(self, channel: int) -> None:
        """Connect ``channel``'s autopilot; must be fast and must not wait on anything remote."""

    @property
    @abstractmethod
    def selected(self) -> int | None:
        """The channel currently connected, None before the first selection."""

    def close(self) -> None:  # noqa: B027 - optional hook, nothing to release by default
        """Release the hardware (the outputs keep their last value where the driver allows)."""


@dataclass(frozen=True)
class Selection:
    """One bridge switch as the simulated bridge recorded it."""

    channel: int
    at: float  # monotonic seconds


class SimulatedBridge(Bridge):
    """Records selections with timestamps and tells listeners which channel drives the motors.

    Listeners (for example the simulated autopilots, so an unconnected standby can be
    modelled) are called synchronously right after the selection is recorded; keep them
    cheap, since the agent measures its switch latency around ``select``.
    """

    def __init__(
        self,
        channels: Iterable[int],
        *,
        initial: int | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.channels = frozenset(channels)
        self._clock = clock
        self._lock = threading.Lock()
        self._listeners: list[Callable[[int], None]] = []
        self.history: list[Selection] = []
        self._selected: int | None = None
        if initial is not None:
            self.select(initial)

    def add_listener(self, listener: Callable[[int], None]) -> None:
        """Call ``listener(channel)`` after every selection (and now, if one was made)."""
        with self._lock:
            self._listeners.append(listener)
            current = self._selected
        if current is not None:
            listener(current)

    def select(self, channel: int) -> None:
        if channel not in self.channels:
            raise BridgeError(f"channel {channel} is not one of {sorted(self.channels)}")
        with self._lock:
            self._selected = channel
            self.history.append(Selection(channel, self._clock()))
            listeners = list(self._listeners)
        for listener in listeners:
            listener(channel)

    @property
    def selected(self) -> int | None:
        return self._selected


class GpioBridge(Bridge):
    """One GPIO output line per autopilot on a Linux GPIO character device (libgpiod v2).

    Line ``channel`` active means that autopilot drives the motors; every other line is
    inactive. ``active_low`` inverts the electrical level for boards wired that way.
    """

    def __init__(
        self,
        chip: str,
        channels: Sequence[int],
        initial: int,
        *,
        active_low: bool = False,
        consumer: str = "roost-agent",
    ) -> None:
        if initial not in channels:
            raise BridgeError(f"initial channel {initial} is not one of {list(channels)}")
        try:
            import gpiod  # noqa: PLC0415 - Linux-only; needed only when this driver is chosen
            from gpiod.line import Direction, Value  # noqa: PLC0415
        except ImportError as exc:  # pragma: no cover - the dependency is declared for Linux
            raise BridgeError(f"the gpiod package is not available: {exc}") from exc
        self._patterns: dict[int, dict[int | str, Any]] = {
            ch: {c: Value.ACTIVE if c == ch else Value.INACTIVE for c in channels}
            for ch in channels
        }
        settings = gpiod.LineSettings(direction=Direction.OUTPUT, active_low=active_low)
        try:
            self._request = gpiod.request_lines(
                chip,
                consumer=consumer,
                config={tuple(channels): settings},
                output_values=self._patterns[initial],
            )
        except (OSError, ValueError) as exc:
            raise BridgeError(
                f"cannot request GPIO lines {list(channels)} on {chip}: {exc}"
            ) from exc
        self._selected: int | None = initial

    def select(self, channel: int) -> None:
        pattern = self._patterns.get(channel)
        if pattern is None:
            raise BridgeError(f"channel {channel} is not one of {sorted(self._patterns)}")
        try:
            self._request.set_values(pattern)
        except OSError as exc:
            raise BridgeError(f"GPIO write for channel {channel} failed: {exc}") from exc
        self._selected = channel

    @property
    def selected(self) -> int | None:
        return self._selected

    def close(self) -> None:
        self._request.release()
