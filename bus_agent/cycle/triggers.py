"""Remote group triggers on their way into the cycle thread.

:class:`TriggerInbox` holds the triggers of groups whose member faulted or was lost on another
host: queued by ``Cycle.trigger_group`` (any thread; it writes an eventfd that wakes the cycle
thread's sleep) or read by the cycle thread itself as datagrams from the trigger socket
(``Cycle.trigger_socket``). The sleep before each deadline waits on both (:meth:`wait`).
"""

from __future__ import annotations

import collections
import os
import select
import socket
import threading

#: At most this many remote triggers wait (older ones are dropped: the reflex is the same).
TRIGGERS_MAX = 256


class TriggerInbox:
    """Remote triggers ``(group, reason)``, the wake eventfd and the trigger socket."""

    def __init__(self) -> None:
        #: Triggers not applied yet, oldest first (the cycle thread pops them).
        self.queue: collections.deque[tuple[str, str]] = collections.deque(maxlen=TRIGGERS_MAX)
        #: Apply a remote group trigger at once in an express exchange (``Cycle.express``) rather
        #: than at the next deadline; False: the next cycle applies it, as before.
        self.express = True
        #: The last sleep found the trigger socket empty when it timed out.
        self.socket_watched = False
        #: eventfd the cycle thread's sleep waits on; :meth:`push` writes it (-1: plain sleep,
        #: e.g. with an injected clock, or before ``start``).
        self.wake_fd = -1
        self._lock = threading.Lock()
        self._sock: socket.socket | None = None

    @property
    def waits(self) -> bool:
        """The sleep waits on the eventfd (and the socket) rather than sleeping plainly."""
        return self.wake_fd >= 0

    def open_wake(self) -> None:
        """Create the wake eventfd (``Cycle.start`` with the real sleep and ``express``)."""
        self.wake_fd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)

    def set_socket(self, sock: socket.socket) -> None:
        sock.setblocking(False)
        self._sock = sock

    def push(self, group: str, reason: str) -> None:
        """Queue a trigger and wake the cycle thread's sleep. Thread-safe."""
        self.queue.append((group, reason))
        with self._lock:
            if self.wake_fd >= 0:
                os.eventfd_write(self.wake_fd, 1)

    def look(self) -> None:
        """Once per cycle: read the socket unless the sleep before this cycle found it empty."""
        if self.socket_watched:
            self.socket_watched = False
        else:
            self.take_datagrams()  # no sleep (late, tick()): look (a failed recv, ~2 us)

    def take_datagrams(self) -> None:
        """Queue the datagrams ``group NUL reason`` (UTF-8) waiting on the trigger socket."""
        sock = self._sock
        if sock is None:
            return
        while True:
            try:
                data = sock.recv(4096)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # the other end is gone: the bridge reports the loss
                return
            if not data:
                return
            group, _, reason = data.decode("utf-8", "replace").partition("\0")
            self.queue.append((group, reason))

    def wait(self, seconds: float) -> bool:
        """Wait ``seconds`` on the eventfd and the socket (:attr:`waits` only); True when a
        trigger ended the wait. select's timeout has microsecond resolution, and the thread's
        1 ns timer slack holds as for a sleep."""
        fd = self.wake_fd
        sock = self._sock
        ready = select.select((fd,) if sock is None else (fd, sock), (), (), seconds)[0]
        if not ready:
            # The socket was empty just now: the cycle need not look (a datagram arriving in the
            # spin or the cycle wakes the next sleep at once, which applies it then).
            self.socket_watched = True
            return False
        if fd in ready:
            try:
                os.eventfd_read(fd)
            except OSError:  # BlockingIOError: read by a wake before; EBADF: closed while stopping
                pass
        if sock is not None and sock in ready:
            self.take_datagrams()
        return True

    def close(self) -> None:
        """Close the eventfd and the socket (with the bus)."""
        with self._lock:  # no push writes to the number once closed (it may be reused)
            fd, self.wake_fd = self.wake_fd, -1
            if fd >= 0:
                os.close(fd)
        if self._sock is not None:
            self._sock.close()
