"""The network of the harness's real nodes: a host bridge, and one network namespace per node.

A kubelet refuses 127.0.0.1 as its node address, and two kubelets on one network stack
would fight over ports (10250) and iptables rules, so every real node gets its own network
namespace, as every companion computer of a fleet has its own network stack. The harness
creates, and owns, everything here:

- a bridge on the host (``rn<tag>``) holding the first address of a private /24 taken from
  10.213.0.0/16 (the first /24 no address of this machine is in yet, chosen under a lock
  so concurrent harnesses differ). The API server's relay listens there and nowhere else;
- per node, a namespace (``roost-<tag>-<index>``) and a veth pair: ``eth0`` inside with
  the node's address (10.213.K.10 + index), the host end (``rn<tag>-<index>``) on the
  bridge. The namespace's only routes are its /24, the Service range (to the bridge,
  so kube-proxy's DNAT of 10.96.0.1 has a route to rewrite) and the other nodes' pod
  subnets, each through that node's address (:meth:`NodeNetwork.route_pods`, a host-gateway
  pod network: a pod or host-network pod reaches a pod on another node directly, or through
  a Service's ClusterIP, which kube-proxy rewrites to such a pod): no default route, so
  pods and host-network pods reach nothing but the harness.

Everything is deleted by name on teardown (the names carry the harness's tag). Needs root
(CAP_NET_ADMIN) and ``ip`` from iproute2.
"""

from __future__ import annotations

import contextlib
import fcntl
import ipaddress
import json
import os
import shutil
import subprocess
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

from roost_localcluster import pki

ADDRESS_SPACE = ipaddress.IPv4Network("10.213.0.0/16")
NODE_HOST_OFFSET = 10
_LOCK = Path("/run/roost-node-network.lock")


class NodeNetworkError(RuntimeError):
    """A namespace, link or address could not be set up; the message has ``ip``'s error."""


def missing_prerequisites() -> list[str]:
    """Why real nodes cannot run here (empty when they can): root, ``ip``, netns support."""
    reasons = []
    if os.geteuid() != 0:
        reasons.append("not root (network namespaces and cgroups need it)")
    if shutil.which("ip") is None:
        reasons.append("no `ip` (iproute2)")
    if not Path("/proc/self/ns/net").exists():
        reasons.append("the kernel has no network namespaces")
    return reasons


def ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    result = subprocess.run(["ip", *args], capture_output=True, text=True, check=False)
    if check and result.returncode != 0:
        raise NodeNetworkError(f"ip {' '.join(args)}: {result.stderr.strip()}")
    return result


def in_namespace(namespace: str, argv: list[str]) -> list[str]:
    """``argv`` run inside ``namespace`` (``ip netns exec`` execs it: the pid stays)."""
    return ["ip", "netns", "exec", namespace, *argv]


@contextlib.contextmanager
def _locked() -> Iterator[None]:
    with _LOCK.open("a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _used_subnets() -> set[ipaddress.IPv4Network]:
    used = set()
    for link in json.loads(ip("-j", "-4", "addr", "show").stdout or "[]"):
        for entry in link.get("addr_info", []):
            address = ipaddress.IPv4Address(entry["local"])
            if address in ADDRESS_SPACE:
                used.add(ipaddress.IPv4Network(f"{address}/24", strict=False))
    return used


@dataclass(frozen=True)
class NodeNetwork:
    """The host bridge of one harness and the /24 its nodes live in."""

    tag: str
    subnet: ipaddress.IPv4Network

    @property
    def bridge(self) -> str:
        return f"rn{self.tag}"

    @property
    def host_address(self) -> str:
        """The bridge's address: where nodes reach the API server (its relay)."""
        return str(self.subnet[1])

    def node_address(self, index: int) -> str:
        return str(self.subnet[NODE_HOST_OFFSET + index])

    def namespace(self, index: int) -> str:
        return f"roost-{self.tag}-{index}"

    def host_veth(self, index: int) -> str:
        return f"rn{self.tag}-{index}"

    @classmethod
    def create(cls, tag: str) -> NodeNetwork:
        """Take the first free /24 of :data:`ADDRESS_SPACE` and put a bridge on it."""
        if len(tag) > 8:
            raise ValueError(f"tag {tag!r} too long for an interface name")
        with _locked():
            used = _used_subnets()
            free = next((s for s in ADDRESS_SPACE.subnets(new_prefix=24) if s not in used), None)
            if free is None:
                raise NodeNetworkError(f"no free /24 left in {ADDRESS_SPACE}")
            network = cls(tag, free)
            ip("link", "add", network.bridge, "type", "bridge")
            try:
                ip("addr", "add", f"{network.host_address}/24", "dev", network.bridge)
                ip("link", "set", network.bridge, "up")
            except NodeNetworkError:
                ip("link", "del", network.bridge, check=False)
                raise
        return network

    def add_node(self, index: int) -> str:
        """Create node ``index``'s namespace, wired to the bridge; returns the namespace."""
        namespace, veth = self.namespace(index), self.host_veth(index)
        ip("netns", "add", namespace)
        try:
            ip("link", "add", veth, "type", "veth", "peer", "name", "eth0", "netns", namespace)
            ip("link", "set", veth, "master", self.bridge, "up")
            inside = ["-n", namespace]
            ip(*inside, "link", "set", "lo", "up")
            ip(*inside, "addr", "add", f"{self.node_address(index)}/24", "dev", "eth0")
            ip(*inside, "link", "set", "eth0", "up")
            ip(*inside, "route", "add", pki.SERVICE_CLUSTER_IP_RANGE, "via", self.host_address)
            # Pods (the CNI bridge inside the namespace) are routed through it.
            sysctl = ["sysctl", "-q", "-w", "net.ipv4.ip_forward=1"]
            subprocess.run(in_namespace(namespace, sysctl), check=True, capture_output=True)
        except (NodeNetworkError, subprocess.CalledProcessError):
            self.remove_node(index)
            raise
        return namespace

    def route_pods(self, index: int, subnet: str, peers: Mapping[int, str]) -> None:
        """Route between node ``index``'s pods (``subnet``) and its ``peers``' (node index ->
        pod subnet), both ways, each through the other node's address on the bridge."""
        for peer, peer_subnet in peers.items():
            via = ("via", self.node_address(peer))
            ip("-n", self.namespace(index), "route", "replace", peer_subnet, *via)
            ip(
                "-n",
                self.namespace(peer),
                "route",
                "replace",
                subnet,
                "via",
                self.node_address(index),
            )

    def unroute_pods(self, subnet: str, peers: Iterable[int]) -> None:
        """Drop the ``peers``' routes to a removed node's pod ``subnet``."""
        for peer in peers:
            ip("-n", self.namespace(peer), "route", "del", subnet, check=False)

    def set_link(self, index: int, *, up: bool) -> None:
        """Bring node ``index``'s link up or down (its host end of the veth): down, the node
        loses the API server and the rest of the harness, as a vehicle loses its WiFi,
        while everything inside its namespace (its loopback) keeps working."""
        ip("link", "set", self.host_veth(index), "up" if up else "down")

    def remove_node(self, index: int) -> None:
        ip("link", "del", self.host_veth(index), check=False)
        ip("netns", "del", self.namespace(index), check=False)

    def delete(self) -> None:
        ip("link", "del", self.bridge, check=False)
