"""Loopback ports the host's NAT table redirects are never given to a test server
(tests/support/natports.py): which rules count, and that the kernel skips a held port
when it picks one for ``bind`` to port 0 (what every test server does).
"""

from __future__ import annotations

import socket

from tests.support.natports import hold, redirected_loopback_ports

# What podman's CNI portmap left behind for a KinD node removed without it (chain
# names shortened),
# and rules that do not redirect 127.0.0.1's TCP ports.
RULES = """\
-P OUTPUT ACCEPT
-A OUTPUT -m addrtype --dst-type LOCAL -j CNI-HOSTPORT-DNAT
-A CNI-DN-1331 -s 127.0.0.1/32 -d 127.0.0.1/32 -p tcp -m tcp --dport 44483 -j CNI-HOSTPORT-SETMARK
-A CNI-DN-1331 -d 127.0.0.1/32 -p tcp -m tcp --dport 44483 -j DNAT --to-destination 10.89.0.33:6443
-A CNI-DN-aa -p tcp -m tcp --dport 40000:40002 -j DNAT --to-destination 10.89.0.9:80
-A CNI-DN-bb -d 10.0.0.5/32 -p tcp -m tcp --dport 8080 -j DNAT --to-destination 10.89.0.10:80
-A CNI-DN-cc -p udp -m udp --dport 5353 -j DNAT --to-destination 10.89.0.11:53
-A PREROUTING -p tcp -m multiport --dports 41000,41005 -j REDIRECT --to-ports 9000
"""


def test_only_redirects_of_loopback_tcp_ports_count() -> None:
    assert redirected_loopback_ports(RULES) == [40000, 40001, 40002, 41000, 41005, 44483]
    assert redirected_loopback_ports("") == []


def test_the_kernel_never_picks_a_held_port_for_port_zero() -> None:
    """Half the ports of a stretch of the ephemeral range held, as the session holds the
    redirected ones: a few thousand binds to port 0 (with ``SO_REUSEADDR``, as the
    dashboard binds) land on none of them, where about one in twenty-eight would
    otherwise."""
    held = hold(list(range(40001, 41001, 2)))
    try:
        ports = {sock.getsockname()[1] for sock in held}
        assert len(ports) > 400  # the others were in use already
        picked = []
        for _ in range(5000):
            with socket.socket() as sock:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                sock.bind(("127.0.0.1", 0))
                picked.append(sock.getsockname()[1])
        assert not ports & set(picked)
    finally:
        for sock in held:
            sock.close()
