"""DeepGTAV transport: how bytes reach the plugin and come back, within a timeout, and reconnects.

Two generations of the plugin: `zmq` (v2 fork: PAIR socket, the client connects; a frame is two
messages, raw bytes then JSON) and `tcp` (classic: a 4-byte little-endian length prefix on every
message and frame part). The plugin streams a frame every 1/rate seconds once a session runs and
silently drops messages it cannot parse, so every receive has a timeout, and `Connection.run`
retries a failed step on a fresh connection with exponential backoff before one clear
RendererError. What the bytes mean is pairedgta/render/deepgtav_protocol.py.
"""
from __future__ import annotations

import logging
import select
import socket
import struct
import time
from collections.abc import Callable
from typing import Any, TypeVar

from pairedgta.errors import ConfigError, RendererError
from pairedgta.render.deepgtav_protocol import ReplyError, decode_frame, encode_message, frame_nbytes, parse_state

log = logging.getLogger(__name__)

T = TypeVar("T")

TRANSPORTS = ("zmq", "tcp")
_MAX_JSON_BYTES = 64 << 20


class Transient(Exception):
    """A failure that a fresh connection may cure (timeout, hang-up, corrupted reply)."""


class _TcpClient:
    """Classic transport: 4-byte little-endian length prefix on each message and frame part."""

    def __init__(self, host: str, port: int, timeout_s: float, max_frame: int) -> None:
        self.where = f"{host}:{port}"
        self.max_frame = max_frame
        try:
            self.sock = socket.create_connection((host, port), timeout=timeout_s)
        except TimeoutError:
            raise Transient(f"connecting timed out after {timeout_s:g} s") from None
        except OSError as exc:
            raise Transient(f"cannot connect ({exc.strerror or exc})") from None
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def send(self, payload: bytes) -> None:
        try:
            self.sock.sendall(struct.pack("<I", len(payload)) + payload)
        except OSError as exc:
            raise Transient(f"sending failed ({exc.strerror or exc})") from None

    def pending(self) -> bool:
        try:
            readable, _, _ = select.select([self.sock], [], [], 0)
        except (OSError, ValueError):
            return True  # let the next read report the problem
        return bool(readable)

    def wait(self, timeout: float) -> bool:
        try:
            readable, _, _ = select.select([self.sock], [], [], max(timeout, 0.0))
        except (OSError, ValueError):
            return True
        return bool(readable)

    def _read(self, n: int, deadline: float, what: str, started: bool) -> bytes:
        buf = bytearray(n)
        view = memoryview(buf)
        got = 0
        while got < n:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise Transient(f"timed out waiting for the {what}" + (" (mid-frame)" if started or got else ""))
            self.sock.settimeout(remaining)
            try:
                k = self.sock.recv_into(view[got:], n - got)
            except TimeoutError:
                continue
            except OSError as exc:
                where = " mid-frame" if started or got else ""
                raise Transient(f"dropped the connection{where} ({exc.strerror or exc})") from None
            if k == 0:
                raise Transient("closed the connection" + (" mid-frame" if started or got else ""))
            got += k
        return bytes(buf)

    def recv_frame(self, timeout: float) -> tuple[bytes, bytes]:
        deadline = time.monotonic() + timeout
        (n,) = struct.unpack("<I", self._read(4, deadline, "frame length", False))
        if n > self.max_frame:
            raise Transient(f"sent an implausible frame length prefix ({n} bytes): garbage on the stream")
        frame = self._read(n, deadline, "frame bytes", True)
        (m,) = struct.unpack("<I", self._read(4, deadline, "JSON length", True))
        if m > _MAX_JSON_BYTES:
            raise Transient(f"sent an implausible JSON length prefix ({m} bytes): garbage on the stream")
        doc = self._read(m, deadline, "JSON document", True)
        return frame, doc

    def close(self, linger_s: float = 0.0) -> None:
        try:
            self.sock.close()  # sendall already handed everything to the kernel
        except OSError:
            pass


class _ZmqClient:
    """v2 transport: PAIR socket, client connects; a frame is two messages (bytes, JSON)."""

    def __init__(self, host: str, port: int, timeout_s: float, max_frame: int) -> None:
        try:
            import zmq
        except ImportError:
            raise ConfigError(
                "renderer.transport=zmq needs pyzmq; install it (pip install pyzmq) or set renderer.transport=tcp"
            ) from None
        self.zmq = zmq
        self.ctx = zmq.Context.instance()
        self.sock = self.ctx.socket(zmq.PAIR)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.setsockopt(zmq.SNDTIMEO, max(int(timeout_s * 1000), 1))
        self.sock.connect(f"tcp://{host}:{port}")

    def send(self, payload: bytes) -> None:
        try:
            self.sock.send(payload)
        except self.zmq.Again:
            raise Transient("sending timed out (no peer accepted the message)") from None
        except self.zmq.ZMQError as exc:
            raise Transient(f"sending failed ({exc})") from None

    def pending(self) -> bool:
        return bool(self.sock.poll(0, self.zmq.POLLIN))

    def wait(self, timeout: float) -> bool:
        return bool(self.sock.poll(max(int(timeout * 1000), 0), self.zmq.POLLIN))

    def recv_frame(self, timeout: float) -> tuple[bytes, bytes]:
        deadline = time.monotonic() + timeout
        if not self.wait(timeout):
            raise Transient("timed out waiting for a frame")
        frame = self.sock.recv(self.zmq.NOBLOCK)
        if not self.wait(deadline - time.monotonic()):
            raise Transient("timed out waiting for the frame's JSON document (mid-frame)")
        doc = self.sock.recv(self.zmq.NOBLOCK)
        return frame, doc

    def close(self, linger_s: float = 0.0) -> None:
        self.sock.close(linger=int(linger_s * 1000))


class Connection:
    """The plugin at host:port over one transport, for frames of width x height.

    `run(what, step)` runs `step` on a live socket (connecting first when there is none); when the
    step raises Transient it drops the socket and tries again on a fresh one, `retries` times with
    exponential backoff, then raises one RendererError naming every distinct reason. `on_fresh` is
    called whenever the socket is replaced or closed: whatever the caller built on the old one (a
    session, a scene) is gone with it.
    """

    def __init__(self, host: str, port: int, transport: str, timeout_s: float, retries: int, backoff_s: float,
                 width: int, height: int, on_fresh: Callable[[], None]) -> None:
        self.host, self.port, self.transport = host, port, transport
        self.timeout_s, self.retries, self.backoff_s = timeout_s, retries, backoff_s
        self.width, self.height = width, height
        self.frame_bytes = frame_nbytes(width, height)
        self.on_fresh = on_fresh
        self._client: _TcpClient | _ZmqClient | None = None
        # seconds spent connecting, in failed attempts and in backoff (already part of the caller's wall
        # time), and the number of retries; the caller resets them per scene
        self.overhead_s = 0.0
        self.retries_used = 0

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    @property
    def connected(self) -> bool:
        return self._client is not None

    def run(self, what: str, fn: Callable[[], T]) -> T:
        """`fn()` on a live socket, retried on a fresh one after a Transient failure (see the class)."""
        attempts = self.retries + 1
        failures: list[str] = []  # distinct reasons, in order of occurrence
        for attempt in range(attempts):
            started = time.perf_counter()
            if attempt:
                self.retries_used += 1
                time.sleep(self.backoff_s * 2 ** (attempt - 1))
            try:
                if self._client is None:
                    self._connect()
                setup = time.perf_counter() - started  # backoff + connecting
                result = fn()
                self.overhead_s += setup
                return result
            except Transient as exc:
                self.overhead_s += time.perf_counter() - started  # the whole failed attempt
                log.warning("DeepGTAV %s at %s, attempt %d/%d: %s", what, self.address, attempt + 1, attempts, exc)
                if str(exc) not in failures:
                    failures.append(str(exc))
                self.drop()
            except BaseException:  # a non-transient error (or an interrupt) may leave the stream mid-frame
                self.drop()
                raise
        raise RendererError(
            f"DeepGTAV server at {self.address} ({self.transport}) failed during {what}: {'; then '.join(failures)} "
            f"(gave up after {attempts} attempt{'s' if attempts > 1 else ''}); check that GTA V with the "
            f"plugin is running and reachable, or raise renderer.timeout_s (now {self.timeout_s:g}) / "
            f"renderer.retries (now {self.retries})"
        )

    def _connect(self) -> None:
        cls = _ZmqClient if self.transport == "zmq" else _TcpClient
        max_frame = max(4 * self.frame_bytes, 64 << 20)
        self._client = cls(self.host, self.port, self.timeout_s, max_frame)
        self.on_fresh()

    def drop(self, linger_s: float = 0.0) -> None:
        """Close the socket (after up to `linger_s` for queued messages to leave)."""
        if self._client is not None:
            self._client.close(linger_s)
        self._client = None
        self.on_fresh()

    def send(self, message: dict[str, Any]) -> None:
        """Validate, encode and send one message (MessageError before anything is sent)."""
        assert self._client is not None
        self._client.send(encode_message(message))

    def next_frame(self, timeout: float | None = None) -> tuple[bytes, dict[str, Any]]:
        """The next frame's bytes and state; a corrupted or out-of-step reply is Transient, a frame of
        the wrong size a FrameSizeError (a misconfiguration, which a retry would not cure)."""
        assert self._client is not None
        frame, raw = self._client.recv_frame(self.timeout_s if timeout is None else timeout)
        if len(frame) != self.frame_bytes:
            if raw[:1] == b"{" and frame[:1] == b"{":
                raise Transient("sent two JSON documents in a row: frame stream out of step")
            decode_frame(frame, self.width, self.height)  # raises FrameSizeError
        try:
            return frame, parse_state(raw)
        except ReplyError as exc:
            raise Transient(str(exc)) from None

    def discard_until(self, deadline: float) -> None:
        """Read and drop frames until `deadline` (the plugin keeps streaming while we wait)."""
        assert self._client is not None
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            if self._client.wait(remaining):
                self.next_frame()
        while self._client.pending():
            self.next_frame()

    def await_state(self, accept: Callable[[dict[str, Any]], str | None], what: str) -> tuple[bytes, dict[str, Any]]:
        """First frame whose state `accept` approves (returns None); a transient error with the
        last objection after `timeout_s`."""
        deadline = time.monotonic() + self.timeout_s
        while True:
            frame, state = self.next_frame(max(min(self.timeout_s, deadline - time.monotonic()), 1e-3))
            objection = accept(state)
            if objection is None:
                return frame, state
            if time.monotonic() >= deadline:
                raise Transient(f"never reported {what} within {self.timeout_s:g} s: {objection}")

    def discard_pending(self) -> None:
        """Read and drop the frames already waiting."""
        assert self._client is not None
        while self._client.pending():
            self.next_frame()


__all__ = ["TRANSPORTS", "Connection", "Transient"]
