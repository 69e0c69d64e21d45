"""``roost-cluster``: the local control plane from the command line.

- ``roost-cluster up --dir .cluster`` builds the binaries if needed, starts the control plane
  detached (the processes outlive the command), waits until healthy, records the pids in
  ``.cluster/state.json`` and prints the kubeconfig path. Interrupting it (Ctrl-C, SIGTERM)
  while it starts stops whatever it had started.
- ``roost-cluster down --dir .cluster`` stops exactly the recorded processes (pid and start
  time must match, so a recycled pid is never signalled).
- ``roost-cluster status --dir .cluster`` shows each component, pid and memory.
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from pathlib import Path
from types import FrameType

from roost_localcluster.controlplane import DATASTORES, ControlPlane, ControlPlaneError, Settings


def _raise_interrupt(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


def up(state_dir: Path, datastore: str = "etcd") -> int:
    existing = ControlPlane.attach(state_dir)
    if existing is not None:
        if all(existing.alive().values()) and existing.ready():
            print(f"roost-cluster: already running ({state_dir})", file=sys.stderr)
            print(existing.kubeconfig)
            return 0
        print("roost-cluster: stopping the remains of a previous cluster", file=sys.stderr)
        existing.stop()
    plane = ControlPlane(state_dir, settings=Settings(datastore=datastore), detached=True)
    previous = signal.signal(signal.SIGTERM, _raise_interrupt)
    started = time.monotonic()
    try:
        plane.start()  # stops what it started if this raises, including KeyboardInterrupt
    except ControlPlaneError as err:
        print(f"roost-cluster: failed to start: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("roost-cluster: interrupted; stopped what had started", file=sys.stderr)
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)
    print(
        f"roost-cluster: ready in {time.monotonic() - started:.1f} s at {plane.server}; "
        f"logs in {plane.logs_dir}; stop with `roost-cluster down --dir {state_dir}`",
        file=sys.stderr,
    )
    print(plane.kubeconfig)
    return 0


def down(state_dir: Path) -> int:
    plane = ControlPlane.attach(state_dir)
    if plane is None:
        print(f"roost-cluster: nothing running in {state_dir}", file=sys.stderr)
        return 0
    pids = plane.pids()
    plane.stop()
    print(f"roost-cluster: stopped {pids}", file=sys.stderr)
    return 0


def status(state_dir: Path) -> int:
    plane = ControlPlane.attach(state_dir)
    if plane is None:
        print(f"roost-cluster: nothing running in {state_dir}")
        return 1
    alive = plane.alive()
    for name, proc in plane.processes.items():
        state = "running" if alive[name] else "STOPPED"
        print(f"{name:25} pid {proc.pid!s:8} {state:8} {proc.rss_bytes() / 2**20:8.0f} MiB")
    print(f"{'api server':25} {plane.server} {'ready' if plane.ready() else 'NOT READY'}")
    print(f"{'kubeconfig':25} {plane.kubeconfig}")
    return 0 if all(alive.values()) else 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="roost-cluster", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for name, help_text in (
        ("up", "start in the background; print the kubeconfig path once healthy"),
        ("down", "stop the processes started by `up`"),
        ("status", "show the recorded processes"),
    ):
        cmd = sub.add_parser(name, help=help_text)
        cmd.add_argument("--dir", type=Path, default=Path(".cluster"), help="state directory")
        if name == "up":
            cmd.add_argument(
                "--datastore",
                choices=DATASTORES,
                default="etcd",
                help="etcd, or kine over SQLite (the datastore K3s uses)",
            )
    args = parser.parse_args(argv)
    state_dir: Path = args.dir.resolve()
    if args.command == "up":
        return up(state_dir, args.datastore)
    command = {"down": down, "status": status}[args.command]
    return command(state_dir)


if __name__ == "__main__":
    raise SystemExit(main())
