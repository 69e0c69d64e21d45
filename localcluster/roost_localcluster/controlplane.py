"""A real Kubernetes control plane as local processes, with kwok as the fleet of kubelets.

Why: Roost is an operator, and only a real API server shows whether its CRD schemas and
CEL rules validate, its RBAC suffices, and its status writes, finalizers, watches and
garbage collection behave. This machine has no container engine (no KinD), so we run the
upstream binaries directly (built by ``build-control-plane.sh``):

====================== =====================================================================
etcd                   storage; ``--unsafe-no-fsync`` because the data is thrown away. Or
                       (``Settings(datastore="kine")``) kine over SQLite, the etcd API K3s
                       stores cluster state with, so Roost is proven on both.
kube-apiserver         RBAC authorisation, client-certificate authentication, service-account
                       tokens signed with our key, every GA API (ValidatingAdmissionPolicy).
kube-controller-manager DaemonSet/Job/ReplicaSet controllers, garbage collector, node
                       lifecycle, service-account and token controllers; each controller uses
                       its own service account (``--use-service-account-credentials``).
kube-scheduler         binds pods to (fake) nodes.
kwok                   plays the kubelet of every Node annotated ``kwok.x-k8s.io/node=fake``:
                       keeps it Ready with leases, marks its pods Running, completes Job pods.
====================== =====================================================================

Everything listens on 127.0.0.1 on ports chosen free at start
(:func:`roost_api.ports.free_port`: below the kernel's ephemeral range, from this process's
own block), so several control planes (other engineers' test runs) coexist.
:class:`ControlPlane` is a context manager for tests; ``roost-cluster up``
(:mod:`roost_localcluster.cli`) starts one detached and records the pids in ``state.json``
so ``roost-cluster down`` stops exactly those.
"""

from __future__ import annotations

import atexit
import contextlib
import http.client
import json
import os
import shutil
import ssl
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Self

import yaml

from roost_api.ports import free_port
from roost_localcluster import binaries, kwoknodes, pki
from roost_localcluster.audit import audit_args
from roost_localcluster.processes import ManagedProcess

KWOK_NODE_ANNOTATION = "kwok.x-k8s.io/node"
KWOK_NODE_ANNOTATION_VALUE = "fake"
POD_CIDR = "10.244.0.1/16"  # kwok hands pod IPs out of this; nothing ever routes to them
SERVICE_ACCOUNT_ISSUER = "https://kubernetes.default.svc.cluster.local"
STATE_FILE = "state.json"
START_ORDER = ("etcd", "kube-apiserver", "kube-controller-manager", "kube-scheduler", "kwok")
DATASTORES = ("etcd", "kine")
_PORT_RETRIES = 3


class ControlPlaneError(RuntimeError):
    """A component did not start or become healthy; the message carries its log tail."""


@dataclass
class Ports:
    """The listening ports of one control plane (all on 127.0.0.1)."""

    etcd_client: int
    """The datastore's etcd API (etcd's client port, or kine's listen address)."""
    etcd_peer: int
    """etcd's peer port, or kine's metrics port (kine's default would be all interfaces)."""
    apiserver: int
    controller_manager: int
    scheduler: int
    kwok: int

    @classmethod
    def pick(cls) -> Ports:
        return cls(*(free_port() for _ in range(6)))


@dataclass(frozen=True)
class Settings:
    """Tunables that change with the size of the simulated fleet.

    The defaults suit tens of nodes. For thousands, lengthen the node lease and the
    controller manager's node-monitor grace period together (kwok renews leases for all
    nodes from one process) and give kwok more parallelism.
    """

    node_lease_duration_s: int = 40
    node_monitor_grace_period_s: int = 50
    eviction_toleration_s: int | None = None
    """The tolerations the API server gives every pod of ``node.kubernetes.io/unreachable``
    and ``not-ready`` (``--default-*-toleration-seconds``; None: its 300 s). With a short
    node-monitor grace period this makes the eviction of pods from a node whose link is
    lost a matter of seconds, for tests of what survives it."""
    ready_timeout_s: float = 120.0
    kube_api_qps: int = 100
    kwok_config: Path | None = None
    """Extra kwok configuration (``--config``), e.g. Stage objects replacing kwok's default
    pod lifecycle; kwok keeps its defaults for any resource kind the file has no stages for."""
    node_status_report_s: float = 0.0
    """Make kwok's nodes write their status every this many seconds, as kubelets with node
    leases do (:mod:`roost_localcluster.kwoknodes`); 0 keeps kwok's own node heartbeat
    (every 20 to 45 s, cheap with tens of nodes)."""
    datastore: str = "etcd"
    """``etcd``, or ``kine`` (SQLite behind kine's etcd API, as in K3s)."""
    audit: bool = False
    """Make the API server record every request's metadata (who, verb, resource, answer;
    no bodies) in ``logs/audit.log``, for counting what each client asks of it
    (:mod:`roost_localcluster.audit`). It costs the API server CPU: leave it off for
    timings."""

    def __post_init__(self) -> None:
        if self.datastore not in DATASTORES:
            raise ValueError(f"datastore must be one of {DATASTORES}, not {self.datastore!r}")

    @property
    def start_order(self) -> tuple[str, ...]:
        """Component names in start order (the datastore's name first)."""
        return (self.datastore, *START_ORDER[1:])


def _args_etcd(bin_dir: Path, ports: Ports, data_dir: Path) -> list[str]:
    client = f"http://127.0.0.1:{ports.etcd_client}"
    peer = f"http://127.0.0.1:{ports.etcd_peer}"
    return [
        str(bin_dir / "etcd"),
        "--name=roost",
        f"--data-dir={data_dir}",
        f"--listen-client-urls={client}",
        f"--advertise-client-urls={client}",
        f"--listen-peer-urls={peer}",
        f"--initial-advertise-peer-urls={peer}",
        f"--initial-cluster=roost={peer}",
        "--unsafe-no-fsync",
        "--log-level=warn",
    ]


def _args_kine(bin_dir: Path, ports: Ports, data_dir: Path) -> list[str]:
    # SQLite in write-ahead-log mode, as K3s configures it; the file is thrown away on stop.
    database = data_dir / "state.db"
    return [
        str(bin_dir / "kine"),
        f"--endpoint=sqlite://{database}?_journal=WAL&cache=shared&_busy_timeout=30000",
        f"--listen-address=127.0.0.1:{ports.etcd_client}",
        f"--metrics-bind-address=127.0.0.1:{ports.etcd_peer}",
    ]


def _args_apiserver(
    bin_dir: Path, ports: Ports, keys: pki.Pki, settings: Settings | None = None
) -> list[str]:
    toleration = settings.eviction_toleration_s if settings is not None else None
    evictions = (
        [
            f"--default-not-ready-toleration-seconds={toleration}",
            f"--default-unreachable-toleration-seconds={toleration}",
        ]
        if toleration is not None
        else []
    )
    return [
        str(bin_dir / "kube-apiserver"),
        f"--etcd-servers=http://127.0.0.1:{ports.etcd_client}",
        "--bind-address=127.0.0.1",
        # Without this the API server advertises the host's default-route address.
        "--advertise-address=127.0.0.1",
        f"--secure-port={ports.apiserver}",
        f"--tls-cert-file={keys.serving_cert}",
        f"--tls-private-key-file={keys.serving_key}",
        f"--client-ca-file={keys.ca_cert}",
        f"--requestheader-client-ca-file={keys.front_proxy_ca_cert}",
        f"--requestheader-allowed-names={pki.FRONT_PROXY.user}",
        "--requestheader-username-headers=X-Remote-User",
        "--requestheader-group-headers=X-Remote-Group",
        "--requestheader-extra-headers-prefix=X-Remote-Extra-",
        f"--proxy-client-cert-file={keys.client_cert(pki.FRONT_PROXY)}",
        f"--proxy-client-key-file={keys.client_key(pki.FRONT_PROXY)}",
        # Node authorisation and NodeRestriction for real kubelets (realnode.py), as on any
        # cluster; kwok is one system:masters client and passes both.
        "--authorization-mode=Node,RBAC",
        "--enable-admission-plugins=NodeRestriction",
        # How the API server reaches a real node's kubelet (logs, exec): by its address.
        f"--kubelet-client-certificate={keys.client_cert(pki.APISERVER_KUBELET)}",
        f"--kubelet-client-key={keys.client_key(pki.APISERVER_KUBELET)}",
        "--kubelet-preferred-address-types=InternalIP,Hostname",
        f"--service-account-issuer={SERVICE_ACCOUNT_ISSUER}",
        f"--service-account-key-file={keys.service_account_pub}",
        f"--service-account-signing-key-file={keys.service_account_key}",
        f"--service-cluster-ip-range={pki.SERVICE_CLUSTER_IP_RANGE}",
        "--allow-privileged=true",
        # No other API servers, and 127.0.0.1 is not routable from pods anyway (kine also
        # needs this: the default reconciler's lease keys break on a loopback address).
        "--endpoint-reconciler-type=none",
        "--profiling=false",
        *evictions,
    ]


def _args_controller_manager(
    bin_dir: Path, ports: Ports, keys: pki.Pki, kubeconfig: Path, settings: Settings
) -> list[str]:
    return [
        str(bin_dir / "kube-controller-manager"),
        f"--kubeconfig={kubeconfig}",
        f"--authentication-kubeconfig={kubeconfig}",
        f"--authorization-kubeconfig={kubeconfig}",
        "--leader-elect=false",
        "--bind-address=127.0.0.1",
        f"--secure-port={ports.controller_manager}",
        f"--tls-cert-file={keys.serving_cert}",
        f"--tls-private-key-file={keys.serving_key}",
        f"--service-account-private-key-file={keys.service_account_key}",
        f"--root-ca-file={keys.ca_cert}",
        "--use-service-account-credentials=true",
        f"--service-cluster-ip-range={pki.SERVICE_CLUSTER_IP_RANGE}",
        f"--node-monitor-grace-period={settings.node_monitor_grace_period_s}s",
        f"--kube-api-qps={settings.kube_api_qps}",
        f"--kube-api-burst={settings.kube_api_qps * 2}",
        "--profiling=false",
    ]


def _args_scheduler(bin_dir: Path, ports: Ports, keys: pki.Pki, kubeconfig: Path) -> list[str]:
    return [
        str(bin_dir / "kube-scheduler"),
        f"--kubeconfig={kubeconfig}",
        f"--authentication-kubeconfig={kubeconfig}",
        f"--authorization-kubeconfig={kubeconfig}",
        "--leader-elect=false",
        "--bind-address=127.0.0.1",
        f"--secure-port={ports.scheduler}",
        f"--tls-cert-file={keys.serving_cert}",
        f"--tls-private-key-file={keys.serving_key}",
        "--profiling=false",
    ]


def _args_kwok(
    bin_dir: Path, ports: Ports, kubeconfig: Path, settings: Settings, node_stages: Path | None
) -> list[str]:
    return [
        str(bin_dir / "kwok"),
        f"--kubeconfig={kubeconfig}",
        f"--manage-nodes-with-annotation-selector={KWOK_NODE_ANNOTATION}={KWOK_NODE_ANNOTATION_VALUE}",
        f"--cidr={POD_CIDR}",
        # Where the API server would dial a fake kubelet (kubectl logs/exec): stay on loopback.
        "--node-ip=127.0.0.1",
        f"--node-lease-duration-seconds={settings.node_lease_duration_s}",
        f"--server-address=127.0.0.1:{ports.kwok}",
        *([f"--config={settings.kwok_config}"] if settings.kwok_config else []),
        *([f"--config={node_stages}"] if node_stages else []),
    ]


def _http_status(
    port: int, path: str, tls: ssl.SSLContext | None = None, timeout_s: float = 2.0
) -> int:
    """Status of GET ``path`` on 127.0.0.1, or 0 when nothing answers (no proxies involved)."""
    conn: http.client.HTTPConnection
    if tls is None:
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout_s)
    else:
        conn = http.client.HTTPSConnection("127.0.0.1", port, timeout=timeout_s, context=tls)
    try:
        conn.request("GET", path)
        return conn.getresponse().status
    except (OSError, http.client.HTTPException):
        return 0
    finally:
        conn.close()


class ControlPlane:
    """etcd, kube-apiserver, kube-controller-manager, kube-scheduler and kwok on 127.0.0.1.

    Use as a context manager (tests) or call :meth:`start` / :meth:`stop`. Everything it
    writes lives in ``state_dir``: ``kubeconfig`` (admin, ``system:masters``), ``pki/``,
    ``logs/<component>.log``, ``etcd/`` or ``kine/`` (the datastore's data, removed on stop)
    and ``state.json`` (ports and pids).

    ``detached=True`` lets the processes outlive this Python process (``roost-cluster up``);
    otherwise they are tied to it (parent-death signal and an ``atexit`` hook) so an
    interrupted test session leaves nothing running.
    """

    def __init__(
        self,
        state_dir: Path | None = None,
        *,
        bin_dir: Path | None = None,
        settings: Settings | None = None,
        detached: bool = False,
    ) -> None:
        self.state_dir = Path(state_dir or tempfile.mkdtemp(prefix="roost-cluster-")).resolve()
        self._bin_dir = bin_dir
        self.settings = settings or Settings()
        self.detached = detached
        self.ports: Ports | None = None
        self.processes: dict[str, ManagedProcess] = {}
        self.pki = pki.Pki(self.state_dir / "pki")

    # ---- paths -------------------------------------------------------------------------
    @property
    def kubeconfig(self) -> Path:
        """Admin kubeconfig (user ``roost-admin`` in ``system:masters``)."""
        return self.state_dir / "kubeconfig"

    @property
    def server(self) -> str:
        assert self.ports is not None, "control plane not started"
        return f"https://127.0.0.1:{self.ports.apiserver}"

    @property
    def logs_dir(self) -> Path:
        return self.state_dir / "logs"

    @property
    def etcd_dir(self) -> Path:
        """The datastore's data: etcd's data directory, or kine's SQLite database."""
        return self.state_dir / self.settings.datastore

    @property
    def start_order(self) -> tuple[str, ...]:
        return self.settings.start_order

    def _component_kubeconfig(self, who: pki.ClientIdentity) -> Path:
        return self.state_dir / "kubeconfigs" / f"{who.file_stem}.kubeconfig"

    # ---- lifecycle ---------------------------------------------------------------------
    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    def start(self) -> None:
        """Start every component in order and return once the cluster is usable.

        Usable means: etcd and the API server report healthy/ready, the controller manager,
        scheduler and kwok answer their health checks, and the ``default`` service account
        exists (so pods can be created). On any failure everything started is stopped.
        """
        bin_dir = self._bin_dir or binaries.ensure_built(self.start_order)
        self.state_dir.mkdir(parents=True, exist_ok=True)
        shutil.rmtree(self.etcd_dir, ignore_errors=True)
        if not self.detached:
            atexit.register(self.stop)
        self.ports = Ports.pick()
        pki.write_pki(self.pki.directory)
        pki.write_kubeconfig(self.kubeconfig, self.pki, self.server, pki.ADMIN)
        try:
            self._start_datastore(bin_dir)
            self.start_apiserver(bin_dir)
            self._start_clients(bin_dir)
            self._wait(
                "the default service account",
                lambda: (
                    self._api_status("/api/v1/namespaces/default/serviceaccounts/default") == 200
                ),
                watch=list(self.processes.values()),
            )
        except BaseException:
            self.stop()
            raise
        self._write_state()

    def _start_datastore(self, bin_dir: Path) -> None:
        data_dir = self.etcd_dir
        if self.settings.datastore == "kine":
            data_dir.mkdir(parents=True)
            self._start("kine", lambda p: _args_kine(bin_dir, p, data_dir))
        else:
            self._start("etcd", lambda p: _args_etcd(bin_dir, p, data_dir))

    def _start_clients(self, bin_dir: Path) -> None:
        """Controller manager, scheduler and kwok only need the API server: start together."""
        assert self.ports is not None
        kcm = self._component_kubeconfig(pki.CONTROLLER_MANAGER)
        sched = self._component_kubeconfig(pki.SCHEDULER)
        kwok = self._component_kubeconfig(pki.KWOK)
        for who, path in ((pki.CONTROLLER_MANAGER, kcm), (pki.SCHEDULER, sched), (pki.KWOK, kwok)):
            pki.write_kubeconfig(path, self.pki, self.server, who)
        starters: dict[str, Callable[[Ports], list[str]]] = {
            "kube-controller-manager": lambda p: _args_controller_manager(
                bin_dir, p, self.pki, kcm, self.settings
            ),
            "kube-scheduler": lambda p: _args_scheduler(bin_dir, p, self.pki, sched),
            "kwok": lambda p: _args_kwok(bin_dir, p, kwok, self.settings, self._node_stages()),
        }
        for name, args in starters.items():
            self._launch(name, args(self.ports))
        for name, args in starters.items():
            self._await_healthy(name, args)

    def _node_stages(self) -> Path | None:
        """kwok's Node stages file when the settings ask for kubelet-like reports."""
        if not self.settings.node_status_report_s:
            return None
        path = self.state_dir / "kwok-node-stages.yaml"
        stages = kwoknodes.node_stages(self.settings.node_status_report_s)
        path.write_text(yaml.safe_dump_all(stages, sort_keys=False))
        return path

    def start_apiserver(self, bin_dir: Path | None = None) -> None:
        """(Re)start the API server on its port with its certificates and wait until ready.

        With :meth:`stop_apiserver` this simulates losing and regaining the control plane
        while the other components (and clients) keep running.
        """
        bin_dir = bin_dir or self._bin_dir or binaries.bin_dir()
        audit = audit_args(self.state_dir, self.logs_dir) if self.settings.audit else []
        self._start(
            "kube-apiserver",
            lambda p: [*_args_apiserver(bin_dir, p, self.pki, self.settings), *audit],
        )
        if self.ports is not None and self.kubeconfig.exists():
            self._write_state()

    def stop_apiserver(self) -> None:
        """Stop only the API server (its port, certificates and etcd data stay)."""
        proc = self.processes.get("kube-apiserver")
        if proc is not None:
            proc.stop()

    def stop(self) -> None:
        """Stop every component this object started (reverse order) and drop etcd's data.

        Safe to call more than once; logs and certificates stay in ``state_dir``.
        """
        for proc in reversed(list(self.processes.values())):  # start order, reversed
            proc.stop()
        self.processes.clear()
        shutil.rmtree(self.etcd_dir, ignore_errors=True)
        with contextlib.suppress(FileNotFoundError):
            (self.state_dir / STATE_FILE).unlink()
        if not self.detached:
            atexit.unregister(self.stop)

    # ---- introspection -----------------------------------------------------------------
    def pids(self) -> dict[str, int]:
        return {n: p.pid for n, p in self.processes.items() if p.pid is not None}

    def alive(self) -> dict[str, bool]:
        return {n: p.alive() for n, p in self.processes.items()}

    def rss_bytes(self) -> int:
        """Resident memory of all control-plane processes together."""
        return sum(p.rss_bytes() for p in self.processes.values())

    def ready(self) -> bool:
        return self._api_status("/readyz") == 200

    # ---- state file (for the detached CLI) --------------------------------------------
    def _write_state(self) -> None:
        assert self.ports is not None
        state = {
            "datastore": self.settings.datastore,
            "ports": asdict(self.ports),
            "kubeconfig": str(self.kubeconfig),
            "processes": [p.to_state() for p in self.processes.values()],
        }
        path = self.state_dir / STATE_FILE
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(state, indent=2) + "\n")
        tmp.replace(path)

    @classmethod
    def attach(cls, state_dir: Path) -> ControlPlane | None:
        """The control plane recorded in ``state_dir/state.json`` (None if there is none).

        The returned object can report status and :meth:`stop` the recorded processes; it
        is detached, so it never stops them by itself.
        """
        path = Path(state_dir) / STATE_FILE
        if not path.exists():
            return None
        state: dict[str, Any] = json.loads(path.read_text())
        settings = Settings(datastore=state.get("datastore", "etcd"))
        plane = cls(Path(state_dir), settings=settings, detached=True)
        plane.ports = Ports(**state["ports"])
        for entry in state["processes"]:
            proc = ManagedProcess.from_state(entry)
            plane.processes[proc.name] = proc
        return plane

    # ---- internals ---------------------------------------------------------------------
    def _env(self, name: str) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items() if k != "KUBECONFIG"}
        if name == "kwok":
            # kwok always loads ~/.kwok/kwok.yaml when present: give it an empty home.
            home = self.state_dir / "kwok-home"
            home.mkdir(exist_ok=True)
            env["HOME"] = str(home)
        return env

    def _launch(self, name: str, argv: list[str]) -> ManagedProcess:
        proc = ManagedProcess(name, argv, self.logs_dir / f"{name}.log")
        proc.launch(self._env(name), die_with_parent=not self.detached)
        self.processes[name] = proc
        return proc

    def _start(self, name: str, args: Callable[[Ports], list[str]]) -> None:
        assert self.ports is not None
        self._launch(name, args(self.ports))
        self._await_healthy(name, args)

    def _await_healthy(self, name: str, args: Callable[[Ports], list[str]]) -> None:
        """Wait for ``name``; if it died because its port was taken meanwhile, move it."""
        assert self.ports is not None
        for attempt in range(_PORT_RETRIES):
            proc = self.processes[name]
            try:
                self._wait(name, lambda: self._healthy(name), watch=[proc])
                return
            except ControlPlaneError:
                port_taken = "address already in use" in proc.log_tail(50)
                if not port_taken or attempt == _PORT_RETRIES - 1 or name == "kube-apiserver":
                    raise
            self._move(name)
            self._launch(name, args(self.ports))

    def _move(self, name: str) -> None:
        assert self.ports is not None
        if name in DATASTORES:
            self.ports.etcd_client, self.ports.etcd_peer = free_port(), free_port()
        else:
            field = {
                "kube-controller-manager": "controller_manager",
                "kube-scheduler": "scheduler",
                "kwok": "kwok",
            }[name]
            setattr(self.ports, field, free_port())

    def _healthy(self, name: str) -> bool:
        assert self.ports is not None
        if name == "etcd":
            return _http_status(self.ports.etcd_client, "/health") == 200
        if name == "kine":
            # kine answers its metrics port once its database is open and it is serving.
            return _http_status(self.ports.etcd_peer, "/metrics") == 200
        if name == "kube-apiserver":
            return self.ready()
        if name == "kube-controller-manager":
            return _http_status(self.ports.controller_manager, "/healthz", self._tls()) == 200
        if name == "kube-scheduler":
            return _http_status(self.ports.scheduler, "/healthz", self._tls()) == 200
        if name == "kwok":
            return _http_status(self.ports.kwok, "/healthz") == 200
        raise KeyError(name)

    def _tls(self, client: pki.ClientIdentity | None = None) -> ssl.SSLContext:
        context = ssl.create_default_context(cafile=str(self.pki.ca_cert))
        if client is not None:
            context.load_cert_chain(self.pki.client_cert(client), self.pki.client_key(client))
        return context

    def _api_status(self, path: str) -> int:
        assert self.ports is not None
        return _http_status(self.ports.apiserver, path, self._tls(pki.ADMIN))

    def _wait(self, what: str, check: Callable[[], bool], watch: list[ManagedProcess]) -> None:
        deadline = time.monotonic() + self.settings.ready_timeout_s
        while True:
            if check():
                return
            for proc in watch:
                if not proc.alive():
                    raise ControlPlaneError(
                        f"{proc.name} exited while waiting for {what}; "
                        f"log {proc.log}:\n{proc.log_tail()}"
                    )
            if time.monotonic() > deadline:
                tails = "\n".join(f"--- {p.name}:\n{p.log_tail(10)}" for p in watch)
                raise ControlPlaneError(
                    f"timed out after {self.settings.ready_timeout_s:.0f} s waiting for {what}\n"
                    f"{tails}"
                )
            time.sleep(0.2)
