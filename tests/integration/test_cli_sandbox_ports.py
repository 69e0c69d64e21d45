"""The sandbox's free-port check against a port this test binds on 127.0.0.1."""

from __future__ import annotations

import socket

from roost_cli.sandbox.runner import port_free


def test_a_bound_port_is_not_free() -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        assert not port_free(taken.getsockname()[1])
