# The C extension _udpbatch.c (built with ROOST_COMPILE=1; see setup.py).

def receive(fd: int, limit: int, /) -> list[tuple[bytes, tuple[str, int] | None, float | None]]: ...
def send(fd: int, data: bytes, address: tuple[str, int], /) -> None: ...
def set_messages(table: dict[int, tuple[int, int, int, int]], /) -> None: ...
def pump(
    bulk_fd: int,
    urgent_fd: int,
    wake_fds: list[int],
    deadlines: tuple[float, float, float, float],
    clients: tuple[tuple[int, tuple[str, int]], ...],
    locked: tuple[str, int] | None,
    sysid: int,
    compid: int,
    agent_comp: int,
    log_busy: bool,
    urgent_returns: bool,
    held: list[tuple[bytes, tuple[str, int] | None, float | None]],
    limit: int,
    routine: bytes,
    /,
) -> tuple[
    list[tuple[bytes, tuple[str, int] | None, float | None, bool, tuple[int, ...] | None]],
    list[tuple[bytes, tuple[str, int] | None, float | None]],
    bool,
]: ...
