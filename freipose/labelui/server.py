"""Running the labeling application with uvicorn: in the foreground or in a background thread."""

from __future__ import annotations

import contextlib
import ipaddress
import logging
import secrets
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

import uvicorn

from freipose.errors import FreiPoseError
from freipose.io.labels import labels_file_lock
from freipose.labelui.app import create_app
from freipose.labelui.frames import FrameCache
from freipose.labelui.store import LabelStore

log = logging.getLogger(__name__)


class ServerStartError(FreiPoseError):
    """The server cannot listen on the requested address."""


@dataclass(frozen=True)
class Running:
    """A labeling server that listens.

    Attributes:
        url: the page's address with the access token (``http://HOST:PORT/?token=...``).
        host: the address it listens on.
        port: the port it listens on (the free one chosen for port 0).
        token: the access token.
    """

    url: str
    host: str
    port: int
    token: str


def bind(host: str, port: int) -> socket.socket:
    """A listening TCP socket on ``host:port`` (port 0: a free port).

    Raises:
        ServerStartError: the address is in use or cannot be bound.
    """
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        raise ServerStartError(
            f"cannot listen on {host}:{port} ({exc}); pass another --port (0 picks a free one) "
            f"or --host"
        ) from exc
    sock.listen(128)
    sock.set_inheritable(True)
    return sock


def network_warning(host: str) -> str | None:
    """What listening on ``host`` exposes, unless it is a loopback address (None then)."""
    try:
        loopback = ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:  # a host name
        loopback = host.lower() == "localhost"
    if loopback:
        return None
    return (
        f"--host {host} makes the page reachable from the network, over plain HTTP: the "
        f"access token still keeps out whoever lacks the URL, but the traffic (the token "
        f"and the labels) is not encrypted; to label on another machine, keep the default "
        f"--host 127.0.0.1 and forward the port over SSH (ssh -L PORT:127.0.0.1:PORT HOST)"
    )


def _url(host: str, port: int, token: str) -> str:
    shown = f"[{host}]" if ":" in host else host
    if host in ("0.0.0.0", "::"):
        shown = socket.gethostname()
    return f"http://{shown}:{port}/?token={token}"


class ServerHandle:
    """A uvicorn server bound to its socket; :meth:`run` serves until stopped."""

    def __init__(self, server: uvicorn.Server, sock: socket.socket):
        self.server = server
        self.sock = sock

    def run(self) -> None:
        """Serve until interrupted (Ctrl-C) or :meth:`stop`."""
        self.server.run(sockets=[self.sock])

    def stop(self) -> None:
        """Ask the server to finish its requests and stop."""
        self.server.should_exit = True


@contextlib.contextmanager
def serving(
    store: LabelStore,
    host: str = "127.0.0.1",
    port: int = 0,
    token: str | None = None,
    *,
    lock: bool = True,
) -> Iterator[tuple[Running, ServerHandle]]:
    """Hold the labels file's lock, bind, and yield the server (not yet serving) and its address.

    Args:
        store: the labels being edited.
        host: the address to listen on.
        port: the port (0: a free one).
        token: the access token (None: a new random one).
        lock: take the lock of ``store.output`` (:func:`~freipose.io.labels.labels_file_lock`);
            False when the caller holds it already (since before it read the file).

    Raises:
        OutputLockedError: another run (a server, a ``freipose labels`` command) writes the
            same labels file, also through a symbolic link.
        ServerStartError: the address cannot be bound.
    """
    token = token or secrets.token_urlsafe(24)
    held = labels_file_lock(store.output) if lock else contextlib.nullcontext()
    with held:
        frames = FrameCache(store.sessions, store.instants)
        sock = bind(host, port)
        try:
            real_port = int(sock.getsockname()[1])
            app = create_app(store, frames, token)
            config = uvicorn.Config(app, log_level="warning", access_log=False, lifespan="off")
            handle = ServerHandle(uvicorn.Server(config), sock)
            yield Running(_url(host, real_port, token), host, real_port, token), handle
        finally:
            sock.close()
            frames.close()


@contextlib.contextmanager
def background_server(
    store: LabelStore, host: str = "127.0.0.1", port: int = 0
) -> Iterator[Running]:
    """Serve ``store`` from a background thread for the duration of the block."""
    with serving(store, host, port) as (running, handle):
        thread = threading.Thread(target=handle.run, daemon=True)
        thread.start()
        deadline = time.monotonic() + 10
        while not handle.server.started and time.monotonic() < deadline:
            time.sleep(0.02)
        try:
            yield running
        finally:
            handle.stop()
            thread.join(timeout=10)
