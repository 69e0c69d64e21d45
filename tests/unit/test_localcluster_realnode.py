"""The real-node harness's pure parts: the node network's names, configurations, certificates.

What each real program is told (kubelet, containerd, kube-proxy, CNI) is checked here
without starting one; ``tests/e2e_node`` starts them.
"""

from __future__ import annotations

import ipaddress
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID

from roost_localcluster import pki
from roost_localcluster.nodenet import NodeNetwork
from roost_localcluster.realnode import (
    RealNode,
    api_endpoint_slice,
    cni_config,
    containerd_config,
    kube_proxy_config,
    kubelet_config,
)


@pytest.fixture
def node(tmp_path: Path) -> RealNode:
    return RealNode(
        name="clover-1",
        index=2,
        address="10.213.7.12",
        namespace="roost-abc123-2",
        directory=tmp_path / "clover-1",
        runtime_dir=Path("/run/roost-node/abc123-2"),
        cgroup="/roost-abc123-2",
    )


def test_network_addresses_and_names_stay_in_the_harness_range() -> None:
    network = NodeNetwork("abc123", ipaddress.IPv4Network("10.213.7.0/24"))
    assert network.host_address == "10.213.7.1"
    assert network.node_address(2) == "10.213.7.12"
    assert all(len(name) <= 15 for name in (network.bridge, network.host_veth(99)))
    assert network.namespace(2) == "roost-abc123-2"


def test_kubelet_config_suits_a_host_without_systemd_swap_off_or_cgroup_v2(
    node: RealNode, tmp_path: Path
) -> None:
    keys = pki.Pki(tmp_path / "pki")
    config = kubelet_config(node, keys, (tmp_path / "s.crt", tmp_path / "s.key"))
    assert config["cgroupDriver"] == "cgroupfs"
    assert config["cgroupRoot"] == node.cgroup  # one root per node: no kubelet sees another's pods
    assert config["failSwapOn"] is False and config["failCgroupV1"] is False
    assert config["address"] == node.address
    assert config["authentication"]["anonymous"]["enabled"] is False
    assert config["authorization"]["mode"] == "Webhook"
    assert config["authentication"]["x509"]["clientCAFile"] == str(keys.ca_cert)
    assert config["containerRuntimeEndpoint"] == f"unix://{node.containerd_socket}"
    assert config["imageGCHighThresholdPercent"] == 100  # imported images cannot be pulled back
    assert len(str(node.containerd_socket)) < 107


def test_containerd_config_restricts_oom_scores_and_keeps_everything_in_the_node_dirs(
    node: RealNode, tmp_path: Path
) -> None:
    node_dir = tmp_path / "node-programs"
    (node_dir / "images").mkdir(parents=True)
    (node_dir / "images" / "roost-pause.name").write_text("localhost/roost-pause:0123\n")
    text = containerd_config(node, node_dir)
    assert "version = 3" in text
    assert "restrict_oom_score_adj = true" in text
    assert 'sandbox = "localhost/roost-pause:0123"' in text
    assert f'address = "{node.containerd_socket}"' in text
    assert f'bin_dirs = ["{node_dir / "cni"}"]' in text
    assert "SystemdCgroup = false" in text
    assert "netns_mounts_under_state_dir = true" in text


def test_cni_and_kube_proxy_use_the_node_pod_subnet(node: RealNode, tmp_path: Path) -> None:
    bridge, portmap = cni_config(node)["plugins"]
    assert bridge["ipam"]["ranges"] == [[{"subnet": "10.214.2.0/24"}]]
    assert bridge["ipMasq"] is True
    assert bridge["ipam"]["dataDir"].startswith(str(node.directory))
    assert portmap["type"] == "portmap"
    proxy = kube_proxy_config(node, tmp_path / "kc")
    assert proxy["mode"] == "iptables" and proxy["hostnameOverride"] == "clover-1"
    assert ipaddress.ip_network(node.pod_subnet).subnet_of(
        ipaddress.ip_network(proxy["clusterCIDR"])
    )


def test_api_endpoint_slice_names_the_kubernetes_service_port() -> None:
    found = api_endpoint_slice("10.213.7.1", 43210)
    assert found["metadata"]["labels"]["kubernetes.io/service-name"] == "kubernetes"
    assert found["endpoints"][0]["addresses"] == ["10.213.7.1"]
    assert found["ports"] == [{"name": "https", "port": 43210, "protocol": "TCP"}]


def test_node_certificates_are_signed_by_the_harness_ca(tmp_path: Path) -> None:
    keys = pki.write_pki(tmp_path / "pki")
    cert_path, _ = pki.issue_kubelet_serving(keys, "clover-1", "10.213.7.12")
    ca = x509.load_pem_x509_certificate(keys.ca_cert.read_bytes())
    serving = x509.load_pem_x509_certificate(cert_path.read_bytes())
    serving.verify_directly_issued_by(ca)
    names = serving.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert names.get_values_for_type(x509.DNSName) == ["clover-1"]
    assert names.get_values_for_type(x509.IPAddress) == [ipaddress.ip_address("10.213.7.12")]
    usage = serving.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
    assert list(usage) == [ExtendedKeyUsageOID.SERVER_AUTH]

    identity = pki.node_identity("clover-1")
    pki.issue_client(keys, identity)
    client = x509.load_pem_x509_certificate(keys.client_cert(identity).read_bytes())
    client.verify_directly_issued_by(ca)
    subject = {a.oid._name: a.value for a in client.subject}
    assert subject == {"commonName": "system:node:clover-1", "organizationName": "system:nodes"}
