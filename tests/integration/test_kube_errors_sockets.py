"""roost_kube.errors: transport failures told apart on real sockets (a refused port, a
listener that never answers). The status decision table is in ``tests/unit``.
"""

from __future__ import annotations

import socket

import pytest
import urllib3

from roost_api.ports import free_port
from roost_kube.errors import (
    ApiUnavailableError,
    from_client_exception,
    transport_of,
)


def test_a_refused_connection_is_refused_not_a_timeout() -> None:
    pool = urllib3.PoolManager(retries=False)
    with pytest.raises(urllib3.exceptions.HTTPError) as caught:
        pool.request("GET", f"http://127.0.0.1:{free_port()}/")
    assert transport_of(caught.value) == "refused"
    mapped = from_client_exception(caught.value, "GET", "/")
    assert isinstance(mapped, ApiUnavailableError) and mapped.status is None
    assert mapped.transport == "refused"


def test_a_server_that_never_answers_is_a_timeout() -> None:
    with socket.create_server(("127.0.0.1", 0)) as silent:  # accepts, never answers
        port = silent.getsockname()[1]
        pool = urllib3.PoolManager(retries=False, timeout=urllib3.Timeout(connect=2, read=0.2))
        with pytest.raises(urllib3.exceptions.HTTPError) as caught:
            pool.request("GET", f"http://127.0.0.1:{port}/")
    assert transport_of(caught.value) == "timeout"
