"""Progress bars for the two long steps: building the control plane, and starting it.

The build is the harness's script (``build-control-plane.sh``, the one place that knows the
versions and the cache); it prints ``[i/n] building NAME`` and ``[i/n] NAME built`` lines,
which become a bar here. A warm cache prints one line and returns at once.

Starting is :meth:`roost_localcluster.controlplane.ControlPlane.start`, which blocks until the
cluster is usable. It must run on the main thread: the harness ties each component's life
to the thread that started it (parent-death signal), so a worker thread ending would stop
the control plane. A small watcher thread reads which components have been launched and
moves the bar meanwhile.
"""

from __future__ import annotations

import re
import subprocess
import threading
from collections import deque
from pathlib import Path

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    SpinnerColumn,
    TextColumn,
    TimeElapsedColumn,
)

from roost_cli.errors import CliError
from roost_localcluster import binaries
from roost_localcluster.controlplane import START_ORDER, ControlPlane, ControlPlaneError

_BUILDING = re.compile(r"\[\d+/\d+\] building (\S+)")
_BUILT = re.compile(r"\[\d+/\d+\] \S+ built")
_WATCH_INTERVAL_S = 0.2


def _progress(console: Console) -> Progress:
    return Progress(
        SpinnerColumn(),
        TextColumn("[progress.description]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=False,
    )


def build_control_plane(console: Console) -> Path:
    """Build the missing control-plane binaries (minutes, cold) and return their directory."""
    directory = binaries.bin_dir()
    missing = binaries.missing(directory)
    if not missing:
        console.print(f"[green]✓[/] control plane binaries cached in {directory}")
        return directory
    console.print(
        f"Building the Kubernetes control plane from source ({', '.join(missing)}) into "
        f"{directory}. This happens once and takes 15 to 30 minutes on two cores."
    )
    tail: deque[str] = deque(maxlen=30)
    with _progress(console) as progress:
        task = progress.add_task("building", total=len(missing))
        proc = subprocess.Popen(
            [str(binaries.BUILD_SCRIPT)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        assert proc.stderr is not None
        for line in proc.stderr:
            tail.append(line.rstrip())
            if match := _BUILDING.search(line):
                progress.update(task, description=f"building {match.group(1)}")
            elif _BUILT.search(line):
                progress.advance(task)
        if proc.wait() != 0:
            raise CliError(
                "building the control plane failed (see the log below); it needs Go 1.25+ "
                "and its module proxy. Retry with `make cluster-build`.\n" + "\n".join(tail)
            )
    still = binaries.missing(directory)
    if still:
        raise CliError(f"the build finished but {still} are missing from {directory}")
    return directory


def start_control_plane(console: Console, plane: ControlPlane) -> None:
    """``plane.start()`` on this thread, with a bar counting the components launched."""
    done = threading.Event()
    steps = len(START_ORDER) + 1  # each component, then "usable" (default service account)
    with _progress(console) as progress:
        task = progress.add_task("starting the control plane", total=steps)

        def watch() -> None:
            while not done.wait(_WATCH_INTERVAL_S):
                launched = [name for name in START_ORDER if name in plane.processes]
                if launched:
                    progress.update(
                        task, completed=len(launched), description=f"started {launched[-1]}"
                    )

        watcher = threading.Thread(target=watch, name="control-plane-progress", daemon=True)
        watcher.start()
        try:
            plane.start()
        except ControlPlaneError as error:
            raise CliError(
                f"the control plane did not start: {error}\nLogs: {plane.logs_dir}"
            ) from error
        finally:
            done.set()
            watcher.join()
        progress.update(task, completed=steps, description=f"control plane ready at {plane.server}")
