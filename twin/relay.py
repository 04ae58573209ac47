"""A host's network link in the twin: a byte relay between its agent and the router that can be cut.

Each host's agent connects to its own relay (a UNIX stream socket, reachable from any network
namespace) instead of the router; the relay forwards bytes to the router's own UNIX socket. With a
PKI every link is TLS, which zenoh runs over TCP only: the relay then listens on a loopback TCP
port and forwards to the router's TLS endpoint, the TLS bytes passing through untouched (the
agent still checks the router's certificate, the router the agent's). Cutting
the link makes the relay swallow every byte in both directions while keeping the sockets open,
like a pulled cable: nothing is closed, so both sides notice only when Zenoh's link lease runs
out (3 s, ``bus_agent.gateway.zenoh_config``). Restoring closes the connections that lived
through the cut (their byte streams lost data) and forwards again; the agent's session
reconnects by itself (background retry of its connect endpoint).

All relays of a twin share one asyncio loop on one thread (:class:`RelayHub`); the twin's
public calls are thread-safe and return once the loop applied them.
"""

from __future__ import annotations

import asyncio
import logging
import os
import threading
from typing import Any, Callable, Union

log = logging.getLogger(__name__)

CHUNK = 65536
#: A UNIX socket path, or a TCP (host, port) (port 0 when listening: the OS picks one).
Address = Union[str, tuple[str, int]]


async def _open(address: Address) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    if isinstance(address, str):
        return await asyncio.open_unix_connection(address)
    return await asyncio.open_connection(*address)


class LinkRelay:
    """One host's link: listens on ``listen``, forwards to the router at ``upstream`` unless cut."""

    def __init__(self, host: str, listen: Address, upstream: Address) -> None:
        self.host = host
        self.listen = listen
        self.upstream = upstream
        self.cut = False
        self.connections = 0            # accepted so far (a reconnect after a restore counts)
        self._server: asyncio.AbstractServer | None = None
        self._writers: set[asyncio.StreamWriter] = set()

    @property
    def endpoint(self) -> str:
        """The Zenoh endpoint the host's agent connects to (a ``tcp/`` one becomes ``tls/`` with a PKI)."""
        if isinstance(self.listen, str):
            return f"unixsock-stream/{self.listen}"
        return f"tcp/{self.listen[0]}:{self.listen[1]}"

    async def start(self) -> None:
        if isinstance(self.listen, str):
            if os.path.exists(self.listen):
                os.unlink(self.listen)
            self._server = await asyncio.start_unix_server(self._accept, path=self.listen)
        else:
            self._server = await asyncio.start_server(self._accept, *self.listen)
            self.listen = (self.listen[0], int(self._server.sockets[0].getsockname()[1]))

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
        self._drop_all()
        if isinstance(self.listen, str):
            try:
                os.unlink(self.listen)
            except FileNotFoundError:
                pass

    def _drop_all(self) -> None:
        for w in list(self._writers):
            w.close()
        self._writers.clear()

    def set_cut(self, cut: bool) -> None:
        """Cut (swallow everything) or restore (drop the connections that lived through the cut)."""
        if self.cut and not cut:
            self._drop_all()
        self.cut = cut
        log.info("twin link %s %s", self.host, "cut" if cut else "restored")

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.connections += 1
        try:
            up_reader, up_writer = await _open(self.upstream)
        except OSError as exc:  # the router is down (killed or restarting): the agent retries
            log.info("twin link %s: router %s unreachable: %s", self.host, self.upstream, exc)
            writer.close()
            return
        self._writers.update((writer, up_writer))
        await asyncio.gather(self._pump(reader, up_writer), self._pump(up_reader, writer), return_exceptions=True)
        for w in (writer, up_writer):
            self._writers.discard(w)
            w.close()

    async def _pump(self, src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
        try:
            while data := await src.read(CHUNK):
                if self.cut:
                    continue  # a pulled cable: the bytes are lost, nobody is told
                dst.write(data)
                await dst.drain()
        except (ConnectionError, OSError):
            pass
        finally:
            dst.close()  # one side ended: end the other (a restore or a peer's close)


class RelayHub:
    """The asyncio thread that runs every :class:`LinkRelay` of one twin."""

    def __init__(self) -> None:
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="twin-relays", daemon=True)
        self._thread.start()
        self.relays: dict[str, LinkRelay] = {}

    def _call(self, fn: Callable[[], Any], timeout_s: float = 10.0) -> Any:
        async def run() -> Any:
            result = fn()
            if asyncio.iscoroutine(result):
                result = await result
            return result
        return asyncio.run_coroutine_threadsafe(run(), self._loop).result(timeout_s)

    def add(self, host: str, listen: Address, upstream: Address) -> LinkRelay:
        relay = LinkRelay(host, listen, upstream)
        self._call(relay.start)
        self.relays[host] = relay
        return relay

    def set_cut(self, host: str, cut: bool) -> None:
        relay = self.relays[host]
        self._call(lambda: relay.set_cut(cut))

    def close(self) -> None:
        """Close every relay and stop the loop (idempotent)."""
        if not self._loop.is_running():
            return
        for relay in list(self.relays.values()):
            try:
                self._call(relay.close)
            except Exception as exc:
                log.warning("twin link %s: close: %s", relay.host, exc)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(10)
        self._loop.close()
