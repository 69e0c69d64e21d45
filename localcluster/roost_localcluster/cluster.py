"""What a test (or the sandbox) holds on to: a kubeconfig plus helpers around it.

:class:`Cluster` works with any kubeconfig, whether the control plane was started by this
process (:class:`~roost_localcluster.controlplane.ControlPlane`, then reachable as
``cluster.control_plane`` for things like :meth:`~ControlPlane.stop_apiserver`) or by
``roost-cluster up`` in the background.
"""

from __future__ import annotations

import subprocess
import time
from collections import Counter
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from roost_kube.client import Kube
from roost_kube.resources import NODES
from roost_localcluster import nodes
from roost_localcluster.audit import AUDIT_LOG, RequestKind, Window
from roost_localcluster.binaries import REPO_ROOT
from roost_localcluster.clients import tool_path
from roost_localcluster.controlplane import ControlPlane


@dataclass
class Cluster:
    """A running cluster reached through ``kubeconfig`` (admin rights)."""

    kubeconfig: Path
    control_plane: ControlPlane | None = None
    _admin: Kube | None = field(default=None, init=False, repr=False, compare=False)

    @classmethod
    def of(cls, plane: ControlPlane) -> Cluster:
        return cls(plane.kubeconfig, plane)

    def kube(self, field_manager: str = "roost-localcluster") -> Kube:
        """A :class:`~roost_kube.client.Kube` for this cluster: the one client layer every
        Roost process, test and benchmark uses."""
        return Kube.from_environment(field_manager, kubeconfig=self.kubeconfig)

    @property
    def admin(self) -> Kube:
        """One client for the harness's own requests (nodes, readiness polls), made on
        first use and kept: a poll must not parse the kubeconfig and open a new TLS
        connection pool every time."""
        if self._admin is None:
            self._admin = self.kube()
        return self._admin

    def audit_window(self) -> Window:
        """Start counting requests (:meth:`audited`); the control plane must have been
        started here with ``Settings(audit=True)``."""
        plane = self.control_plane
        if plane is None or not plane.settings.audit:
            raise RuntimeError("counting requests needs a control plane with Settings(audit=True)")
        return Window.open(plane.logs_dir / AUDIT_LOG)

    def audited(self, window: Window) -> Counter[RequestKind]:
        """The requests every client made from :meth:`audit_window` until now, by kind."""
        return window.close(
            lambda marker: self.kubectl("get", "namespace", marker, "--ignore-not-found")
        )

    def _run(
        self, tool: str, args: Iterable[str], check: bool, input_text: str | None, timeout_s: float
    ) -> subprocess.CompletedProcess[str]:
        argv = [str(tool_path(tool)), "--kubeconfig", str(self.kubeconfig), *args]
        result = subprocess.run(
            argv, input=input_text, capture_output=True, text=True, timeout=timeout_s, check=False
        )
        if check and result.returncode != 0:
            raise subprocess.CalledProcessError(
                result.returncode, argv, output=result.stdout, stderr=result.stderr
            )
        return result

    def kubectl(
        self, *args: str, check: bool = True, input_text: str | None = None, timeout_s: float = 120
    ) -> subprocess.CompletedProcess[str]:
        """Run kubectl against this cluster; output is captured (``.stdout``/``.stderr``).

        ``check=True`` raises CalledProcessError (with stderr) on a non-zero exit.
        """
        return self._run("kubectl", args, check, input_text, timeout_s)

    def helm(
        self, *args: str, check: bool = True, input_text: str | None = None, timeout_s: float = 300
    ) -> subprocess.CompletedProcess[str]:
        """Run helm against this cluster, like :meth:`kubectl`."""
        return self._run("helm", args, check, input_text, timeout_s)

    def install_crds(self, directory: Path = REPO_ROOT / "crds", timeout_s: float = 60) -> None:
        """``kubectl apply`` every CRD in ``directory`` and wait until all are Established."""
        self.kubectl("apply", "-f", str(directory))
        # A CRD created a moment ago may have no status.conditions yet, which makes
        # `kubectl wait` fail at once instead of waiting: retry until the deadline.
        deadline = time.monotonic() + timeout_s
        while True:
            result = self.kubectl(
                "wait",
                "--for=condition=Established",
                "--timeout=5s",
                "-f",
                str(directory),
                check=False,
            )
            if result.returncode == 0:
                return
            if time.monotonic() > deadline:
                raise subprocess.CalledProcessError(
                    result.returncode, result.args, output=result.stdout, stderr=result.stderr
                )
            time.sleep(0.5)

    def as_service_account(
        self, namespace: str, name: str, kubeconfig: Path, duration: str = "1h"
    ) -> Cluster:
        """This cluster as seen by a service account: a kubeconfig with a fresh bound token.

        The token comes from the TokenRequest API, so it is signed with the control plane's
        service-account key and authorised by RBAC exactly as a pod's token would be (unlike
        ``kubectl --as``, which needs and tests impersonation rights).
        """
        token = self.kubectl(
            "create", "token", name, "-n", namespace, f"--duration={duration}"
        ).stdout.strip()
        admin = yaml.safe_load(self.kubeconfig.read_text())
        cluster_entry = admin["clusters"][0]
        user = f"system:serviceaccount:{namespace}:{name}"
        context = {"cluster": cluster_entry["name"], "user": user, "namespace": namespace}
        config_doc = {
            "apiVersion": "v1",
            "kind": "Config",
            "clusters": [cluster_entry],
            "users": [{"name": user, "user": {"token": token}}],
            "contexts": [{"name": user, "context": context}],
            "current-context": user,
        }
        kubeconfig.parent.mkdir(parents=True, exist_ok=True)
        kubeconfig.write_text(yaml.safe_dump(config_doc, sort_keys=False))
        kubeconfig.chmod(0o600)
        return Cluster(kubeconfig, self.control_plane)

    def add_node(
        self,
        name: str,
        *,
        labels: Mapping[str, str] | None = None,
        annotations: Mapping[str, str] | None = None,
        cpu: str = "4",
        memory: str = "8Gi",
        pods: int = 110,
        taints: Iterable[Mapping[str, str]] = (),
        wait: bool = True,
        timeout_s: float = 60.0,
    ) -> dict[str, Any]:
        """Create a kwok-managed fake node (see :func:`roost_localcluster.nodes.fake_node`).

        With ``wait`` (the default) return only once the node is Ready and schedulable.
        Returns the manifest that was created.
        """
        manifest = nodes.fake_node(
            name,
            labels=labels,
            annotations=annotations,
            cpu=cpu,
            memory=memory,
            pods=pods,
            taints=taints,
        )
        kube = self.admin
        kube.create(manifest)
        if wait:
            nodes.wait_nodes_ready(kube, [name], timeout_s)
        return manifest

    def wait_nodes_ready(self, names: Iterable[str], timeout_s: float = 120.0) -> None:
        nodes.wait_nodes_ready(self.admin, names, timeout_s)

    def delete_node(self, name: str) -> None:
        self.admin.delete(NODES, name)


class FakeNodes:
    """Adds fake nodes to a cluster and deletes all of them on :meth:`cleanup`.

    A pytest fixture of any scope is ``pool = FakeNodes(cluster); yield pool;
    pool.cleanup()``; calling ``pool(name, **kwargs)`` is :meth:`Cluster.add_node`.
    """

    def __init__(self, cluster: Cluster) -> None:
        self.cluster = cluster
        self.names: list[str] = []

    def __call__(self, name: str, **kwargs: Any) -> dict[str, Any]:
        self.names.append(name)  # before creating: a node that never gets Ready is removed too
        return self.cluster.add_node(name, **kwargs)

    def cleanup(self) -> None:
        while self.names:
            self.cluster.kubectl("delete", "node", self.names.pop(), "--ignore-not-found")
