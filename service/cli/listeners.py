"""One listening socket per API process (SO_REUSEPORT): the kernel, not a race between processes, places connections.

uvicorn's own multi-process mode binds one socket in its supervisor and lets every process accept from it: which
process takes a connection is a race between their event loops, and a keep-alive connection then stays where it
landed. Under `posemetry bench load` (each camera on a keep-alive connection of its own) the two API processes held
28 and 5 of the connections in one run and 16 and 17 in another, and the busier process's requests queued behind
its own interpreter lock while the other process idled (docs/benchmarks/load.md, "stop 33"). With a socket of its
own in each process, bound with SO_REUSEPORT to the same address, Linux picks the listener for each new connection
by a hash of its addresses, whatever the processes are doing.

uvicorn's supervisor (restarts, health pings, signals) is kept: it hands each process a picklable stand-in instead
of a socket, which opens the process's own socket when the process unpickles it. The supervisor itself holds a
bound, never listening, socket on the address, so the port is taken (and a port of 0 resolved) before any process
starts, and no connection is ever queued on it. Elsewhere than Linux (where SO_REUSEPORT does not balance) the
shared socket stays.

A process that dies drops the connections still waiting in its own accept queue (the client sees a reset and
retries); with the shared socket they waited for the other processes. Deaths are rare and the supervisor restarts
the process; the balance is worth it.
"""

from __future__ import annotations

import socket
import sys
from dataclasses import dataclass
from typing import Any

BALANCES = sys.platform == "linux" and hasattr(socket, "SO_REUSEPORT")


def reuse_port_socket(family: int, address: tuple[Any, ...]) -> socket.socket:
    """A TCP socket bound to `address` with SO_REUSEPORT (and SO_REUSEADDR, as uvicorn sets), not listening yet."""
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        sock.bind(address)
    except BaseException:
        sock.close()
        raise
    return sock


@dataclass(frozen=True)
class OwnListener:
    """Stands in for the socket uvicorn's supervisor passes to each API process: unpickled in the process (spawn),
    it becomes that process's own SO_REUSEPORT socket on `address`."""

    family: int
    address: tuple[Any, ...]

    def __reduce__(self) -> tuple[Any, ...]:
        return (reuse_port_socket, (self.family, self.address))


def reserve(host: str, port: int) -> tuple[socket.socket, OwnListener]:
    """The supervisor's placeholder socket on (host, port), and the stand-in for the processes' own sockets on the
    address it got (the actual port when `port` is 0)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    reserved = reuse_port_socket(family, (host, port))
    return reserved, OwnListener(family, reserved.getsockname()[:2])
