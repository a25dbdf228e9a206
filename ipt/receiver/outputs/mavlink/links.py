"""The thin links under the MAVLink output: a raw serial port (termios, non-blocking on the event loop) and
an asyncio UDP endpoint, both handing the bytes they read to a callback; and pymavlink's dialect modules.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import fcntl
import importlib
import os
import re
import termios
from collections.abc import Callable
from types import ModuleType
from typing import TYPE_CHECKING

from ipt.config.receiver import LinkSpec
from ipt.receiver.outputs.mavlink.frames import MavlinkError

if TYPE_CHECKING:
    pass

MAX_SERIAL_BUFFER_BYTES = 16 * 1024
"""Bytes queued for a serial port that does not keep up; further messages are dropped (and counted)."""


def load_dialect(name: str) -> ModuleType:
    """pymavlink's MAVLink 2 module for dialect ``name``; :class:`MavlinkError` if unknown or unsuitable."""
    if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", name):
        raise MavlinkError(f"unknown MAVLink dialect {name!r}")
    try:
        module = importlib.import_module(f"pymavlink.dialects.v20.{name}")
    except ImportError:
        raise MavlinkError(f"unknown MAVLink dialect {name!r} (e.g. common, ardupilotmega, development)") from None
    if not hasattr(module, "MAVLink_odometry_message"):
        raise MavlinkError(f"MAVLink dialect {name!r} has no ODOMETRY message; use common or ardupilotmega")
    return module


class SerialPort:
    """A raw serial port on the event loop: non-blocking reads and writes, exclusive use."""

    def __init__(self, spec: LinkSpec, on_bytes: Callable[[bytes], None], on_broken: Callable[[str], None]) -> None:
        self.spec, self.on_bytes, self.on_broken = spec, on_bytes, on_broken
        self.fd: int | None = None
        self._out = bytearray()
        self._loop: asyncio.AbstractEventLoop | None = None

    def open(self, loop: asyncio.AbstractEventLoop) -> None:
        dev = self.spec.device
        try:
            fd = os.open(dev, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        except FileNotFoundError:
            raise MavlinkError(f"{dev}: no such serial port") from None
        except PermissionError:
            raise MavlinkError(f"{dev}: permission denied (is this user in the dialout group?)") from None
        except OSError as exc:
            if exc.errno == errno.EBUSY:
                raise MavlinkError(f"{dev}: busy (another program has it open)") from None
            raise MavlinkError(f"{dev}: cannot open ({exc.strerror or exc})") from None
        try:
            if not os.isatty(fd):
                raise MavlinkError(f"{dev}: not a serial port")
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise MavlinkError(
                    f"{dev}: busy (another program holds it: a serial console, ModemManager, mavproxy?)"
                ) from None
            speed = getattr(termios, f"B{self.spec.baud}")
            attrs = termios.tcgetattr(fd)
            # Raw 8N1, no flow control, no echo, no line editing (what tty.setraw does, plus the speed).
            attrs[0] = 0  # iflag
            attrs[1] = 0  # oflag
            attrs[2] = (attrs[2] & ~(termios.CSIZE | termios.PARENB | termios.CSTOPB | termios.CRTSCTS)) | (
                termios.CS8 | termios.CREAD | termios.CLOCAL
            )
            attrs[3] = 0  # lflag
            attrs[4] = attrs[5] = speed
            attrs[6][termios.VMIN] = 0
            attrs[6][termios.VTIME] = 0
            termios.tcsetattr(fd, termios.TCSANOW, attrs)
            with contextlib.suppress(OSError):
                fcntl.ioctl(fd, termios.TIOCEXCL)  # nobody else may open it while we have it
        except MavlinkError:
            os.close(fd)
            raise
        except (OSError, termios.error) as exc:
            os.close(fd)
            raise MavlinkError(f"{dev}: cannot set it up as a serial port ({exc})") from None
        self.fd, self._loop = fd, loop
        loop.add_reader(fd, self._readable)

    def _readable(self) -> None:
        if self.fd is None:
            return
        try:
            data = os.read(self.fd, 4096)
        except BlockingIOError:
            return
        except OSError as exc:
            self.on_broken(f"{self.spec.device}: read failed ({exc.strerror or exc})")
            return
        if data:
            self.on_bytes(data)

    def _writable(self) -> None:
        if self.fd is None or self._loop is None:
            return
        try:
            n = os.write(self.fd, self._out)
        except BlockingIOError:
            return
        except OSError as exc:
            self.on_broken(f"{self.spec.device}: write failed ({exc.strerror or exc})")
            return
        del self._out[:n]
        if not self._out:
            self._loop.remove_writer(self.fd)

    def send(self, data: bytes) -> bool:
        """Queue ``data``; False (dropped) if the port is closed or far behind."""
        if self.fd is None or self._loop is None:
            return False
        if self._out:
            if len(self._out) + len(data) > MAX_SERIAL_BUFFER_BYTES:
                return False
            self._out += data
            return True
        try:
            n = os.write(self.fd, data)
        except BlockingIOError:
            n = 0
        except OSError as exc:
            self.on_broken(f"{self.spec.device}: write failed ({exc.strerror or exc})")
            return False
        if n < len(data):
            self._out += data[n:]
            self._loop.add_writer(self.fd, self._writable)
        return True

    def close(self) -> None:
        fd, self.fd = self.fd, None
        if fd is None:
            return
        if self._loop is not None:
            with contextlib.suppress(Exception):
                self._loop.remove_reader(fd)
            with contextlib.suppress(Exception):
                self._loop.remove_writer(fd)
        self._out.clear()
        with contextlib.suppress(OSError):
            os.close(fd)


class UdpProtocol(asyncio.DatagramProtocol):
    def __init__(self, link: UdpLink) -> None:
        self.link = link

    def datagram_received(self, data: bytes, addr: tuple[str | int, ...]) -> None:
        self.link.on_bytes(data)

    def error_received(self, exc: Exception) -> None:
        self.link.on_error(exc)


class UdpLink:
    """A connected UDP endpoint: datagrams to HOST:PORT, replies from it."""

    def __init__(self, spec: LinkSpec, on_bytes: Callable[[bytes], None], on_error: Callable[[BaseException], None]):
        self.spec, self.on_bytes, self.on_error = spec, on_bytes, on_error
        self.transport: asyncio.DatagramTransport | None = None

    async def open(self, loop: asyncio.AbstractEventLoop) -> None:
        try:
            transport, _ = await loop.create_datagram_endpoint(
                lambda: UdpProtocol(self), remote_addr=(self.spec.host, self.spec.port)
            )
        except OSError as exc:
            raise MavlinkError(f"{self.spec}: {exc.strerror or exc}") from None
        self.transport = transport

    def send(self, data: bytes) -> bool:
        t = self.transport
        if t is None or t.is_closing():
            return False
        try:
            t.sendto(data)
        except OSError as exc:
            self.on_error(exc)
            return False
        return True

    def close(self) -> None:
        t, self.transport = self.transport, None
        if t is not None:
            t.close()
