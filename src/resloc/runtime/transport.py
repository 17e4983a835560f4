"""Zenoh transport: explicit session configuration, verified links, one inbox per process.

Zenoh's defaults are wrong for a robot team on a shared network (measured): a default
session listens on every interface and joins UDP multicast scouting, its default congestion
control drops samples silently under load, ``zenoh.open()`` returns a session even when no
link comes up, peers do not relay for each other, and a process with a Python subscriber
hangs at exit unless its session is closed. So:

* every session gets an explicit configuration (:func:`zenoh_config`): the given
  ``listen`` / ``connect`` endpoints only, multicast scouting and gossip off, a connect
  timeout;
* the team is a star around one router: ``resloc swarm`` opens a Zenoh session in
  ``router`` mode on its ``--listen`` endpoint (or every process connects to an external
  ``zenohd`` with ``--connect``); the world, radio, robots and recorder are ``client``
  sessions of that router, which relays between them;
* :func:`open_session` waits until the client sees its router and raises
  :class:`TransportError` otherwise;
* every publisher uses ``CongestionControl.BLOCK`` and reliable delivery: the only losses
  are the radio model's (and, in realtime mode, the age limit's);
* :class:`Bus` closes its session in ``close()``, which every process calls in ``finally``.
"""

from __future__ import annotations

import json
import queue
import re
import socket
import time
from collections.abc import Callable
from typing import Any

from resloc.errors import ResLocError
from resloc.runtime.messages import Codec, Kind, Verifier

__all__ = [
    "Bus",
    "TransportError",
    "check_endpoint",
    "free_endpoint",
    "open_session",
    "zenoh_config",
]

_ENDPOINT = re.compile(r"^(tcp|udp|tls|quic)/(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.\-]+):(\d{1,5})$")


class TransportError(ResLocError):
    """A Zenoh session could not be opened or linked (message names the endpoint)."""


def check_endpoint(endpoint: str, option: str) -> str:
    """Validate a Zenoh endpoint ``proto/host:port`` (raises a one-line :class:`ConfigError`)."""
    from resloc.errors import ConfigError

    m = _ENDPOINT.match(endpoint.strip())
    if not m or not 0 < int(m.group(3)) < 65536:
        raise ConfigError(
            f"{option} {endpoint!r}: not a Zenoh endpoint; use e.g. tcp/127.0.0.1:7447"
        )
    return endpoint.strip()


def free_endpoint(host: str = "127.0.0.1") -> str:
    """A TCP endpoint on ``host`` with a port that is free right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return f"tcp/{host}:{s.getsockname()[1]}"


def zenoh_config(
    mode: str, listen: list[str], connect: list[str], connect_timeout_ms: int = 5000
) -> Any:
    """An explicit Zenoh configuration: only these endpoints, no multicast, no gossip."""
    import zenoh

    conf = {
        "mode": mode,
        "listen": {"endpoints": list(listen)},
        "connect": {"endpoints": list(connect), "timeout_ms": int(connect_timeout_ms)},
        "scouting": {
            "multicast": {"enabled": False},
            "gossip": {"enabled": False},
        },
    }
    return zenoh.Config.from_json5(json.dumps(conf))


def open_session(mode: str, listen: list[str], connect: list[str], timeout_s: float = 10.0) -> Any:
    """Open a Zenoh session and verify it is linked to a router (or, for the router itself,
    listening).

    Raises
    ------
    TransportError
        The session cannot open or no link comes up within ``timeout_s``.
    """
    import zenoh

    try:
        session = zenoh.open(zenoh_config(mode, listen, connect, int(timeout_s * 1000)))
    except zenoh.ZError as exc:
        where = ", ".join(connect or listen) or "(no endpoint)"
        first = str(exc).splitlines()[0].split(" at ")[0]
        raise TransportError(f"cannot open a Zenoh session on {where}: {first}") from None
    if mode == "router" or not connect:
        return session
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if list(session.info.routers_zid()) or list(session.info.peers_zid()):
            return session
        time.sleep(0.02)
    session.close()
    raise TransportError(f"no Zenoh link to {', '.join(connect)} within {timeout_s:g} s")


class Bus:
    """One process's connection: authenticated publishing and one inbox of frames.

    Everything received (frames and liveliness changes) lands in :attr:`inbox`, a
    ``queue.Queue`` of ``(tag, key, payload)`` items, consumed by the process's own thread
    (Zenoh's callbacks run on Zenoh's threads and only enqueue). Frames are verified by the
    consumer with :attr:`verifier`.
    """

    def __init__(
        self, session: Any, run_id: str, codec: Codec, verifier: Verifier, prefix: str = "resloc"
    ) -> None:
        self.session = session
        self.root = f"{prefix}/{run_id}"
        self.codec = codec
        self.verifier = verifier
        self.inbox: queue.Queue = queue.Queue()
        self._publishers: dict[str, Any] = {}
        self._handles: list[Any] = []
        self.sent_frames = 0
        self.sent_bytes = 0

    def key(self, *parts: Any) -> str:
        return "/".join([self.root, *(str(p) for p in parts)])

    def declare(self, key: str) -> Any:
        """The publisher of ``key`` (reliable, blocking congestion control), declared once."""
        import zenoh

        pub = self._publishers.get(key)
        if pub is None:
            pub = self.session.declare_publisher(
                key,
                congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE,
            )
            self._publishers[key] = pub
        return pub

    def put(self, key: str, frame: bytes) -> int:
        """Publish ``frame`` on ``key`` (reliable, blocking congestion control)."""
        self.declare(key).put(frame)
        self.sent_frames += 1
        self.sent_bytes += len(frame)
        return len(frame)

    def send(self, key: str, kind: Kind, step: int, body: dict, sender: int | None = None) -> bytes:
        """Encode, authenticate and publish one message; returns the frame."""
        frame = self.codec.encode(kind, step, body, key, sender=sender)
        self.put(key, frame)
        return frame

    def subscribe(self, key: str, tag: str = "frame") -> None:
        """Queue every sample on ``key`` (may contain wildcards) into :attr:`inbox`."""
        inbox = self.inbox

        def on_sample(sample: Any) -> None:
            inbox.put((tag, str(sample.key_expr), sample.payload.to_bytes()))

        self._handles.append(self.session.declare_subscriber(key, on_sample))

    def watch_liveliness(self, key: str) -> None:
        """Queue ``("alive", key, True/False)`` for every token under ``key`` (with the
        tokens already alive)."""
        import zenoh

        inbox = self.inbox

        def on_change(sample: Any) -> None:
            inbox.put(("alive", str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT))

        self._handles.append(
            self.session.liveliness().declare_subscriber(key, on_change, history=True)
        )

    def declare_alive(self, key: str) -> None:
        """A liveliness token: its loss tells everyone this process died."""
        self._handles.append(self.session.liveliness().declare_token(key))

    def open(self, item: tuple[str, str, Any]):
        """Verify an inbox frame item (received on its key expression); None if rejected."""
        return self.verifier.open(item[2], item[1])

    def get(self, timeout: float | None) -> tuple[str, str, Any] | None:
        """Next inbox item, or None after ``timeout`` seconds."""
        try:
            return self.inbox.get(timeout=timeout)
        except queue.Empty:
            return None

    def close(self) -> None:
        """Undeclare everything and close the session (a process must call this to exit)."""
        for handle in [*self._handles, *self._publishers.values()]:
            try:
                handle.undeclare()
            except Exception:  # already gone with a broken session
                pass
        self._handles.clear()
        self._publishers.clear()
        try:
            self.session.close()
        except Exception:
            pass


def drain_until(
    bus: Bus, done: Callable[[], bool], handle: Callable[[tuple], None], timeout: float
) -> bool:
    """Handle inbox items until ``done()`` or ``timeout`` seconds pass; returns ``done()``."""
    deadline = time.monotonic() + timeout
    while not done():
        left = deadline - time.monotonic()
        if left <= 0:
            return done()
        item = bus.get(min(left, 0.25))
        if item is not None:
            handle(item)
    return True
