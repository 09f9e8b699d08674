"""Serving a recording to browsers: rerun's web viewer and gRPC proxy, bound to one address (loopback by default).

rerun-sdk's in-process ``serve_grpc`` / ``serve_web_viewer`` listen on every interface (0.0.0.0) with no way to choose,
so anyone on the network could read the scene. The ``rerun`` program that the SDK installs takes ``--bind``: occkit
starts it as a child process serving both ports on the chosen address, checks the ports before, connects the
recording to it, and stops it on exit. This module imports no rerun, so the checks run before anything heavy.
"""

from __future__ import annotations

import ipaddress
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO
from urllib.parse import quote

from occkit.errors import UsageError

__all__ = ["LOOPBACK", "ViewerServer", "check_bind", "check_port_free", "is_loopback", "start_server"]

#: The default bind address: only this machine can connect.
LOOPBACK = "127.0.0.1"


def is_loopback(address: str) -> bool:
    """True for an address only this machine can reach (127.0.0.0/8, ::1, ``localhost``)."""
    if address == "localhost":
        return True
    return ipaddress.ip_address(address).is_loopback


def check_bind(address: str) -> str:
    """``--bind``: an IPv4 or IPv6 address (or ``localhost``) this machine can listen on."""
    if address != "localhost":
        try:
            ipaddress.ip_address(address)
        except ValueError:
            raise UsageError(f"--bind {address!r} is not an IP address (e.g. 127.0.0.1, 0.0.0.0 or ::)") from None
    return address


def check_port_free(address: str, port: int, option: str) -> None:
    """Refuse ``option`` when ``port`` cannot be listened on at ``address`` (another program has it, or it is
    privileged)."""
    family = socket.AF_INET6 if ":" in address else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        # As the server binds (SO_REUSEADDR): a port left in TIME_WAIT by a server that just stopped is free.
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((address, port))
        except OSError as error:
            why = "is already in use" if error.errno in (98, 48, 10048) else f"cannot be used ({error.strerror})"
            raise UsageError(f"{option} {port} {why} on {address}: choose another port with {option}") from None


@dataclass
class ViewerServer:
    """A running ``rerun`` server: its child process and addresses. ``stop()`` ends it (also on Ctrl-C)."""

    process: subprocess.Popen
    log: IO[bytes]
    """What the server prints (a file, not a pipe: a pipe nobody reads would stall a server that runs for hours)."""
    bind: str
    web_port: int
    grpc_port: int

    @property
    def host(self) -> str:
        """How this machine reaches the server (loopback when it listens on every interface)."""
        if self.bind in ("0.0.0.0", "::"):  # noqa: S104 - the address it listens on, not one it binds here
            return "localhost"
        return f"[{self.bind}]" if ":" in self.bind else self.bind

    @property
    def grpc_url(self) -> str:
        """The proxy URL a logging SDK or a native viewer connects to."""
        return f"rerun+http://{self.host}:{self.grpc_port}/proxy"

    @property
    def web_url(self) -> str:
        """The web viewer's address, opening the served recording."""
        return f"http://{self.host}:{self.web_port}/?url={quote(self.grpc_url, safe='')}"

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
        self.log.close()

    def last_words(self) -> str:
        """The last line the server printed (why it stopped), or its exit code."""
        self.log.seek(0)
        said = self.log.read().decode(errors="replace").strip().splitlines()
        return said[-1] if said else f"exit code {self.process.returncode}"


def _rerun_program() -> str:
    """The ``rerun`` executable itself, as the ``rerun_cli`` package that rerun-sdk installs ships it (its ``rerun``
    script is a Python wrapper whose own child would outlive a stopped wrapper), else ``rerun`` on PATH."""
    import importlib.util

    spec = importlib.util.find_spec("rerun_cli")
    if spec is not None and spec.origin is not None:
        folder = Path(spec.origin).parent
        for candidate in (folder / "Rerun.app" / "Contents" / "MacOS" / "Rerun", folder / "rerun",
                          folder / "rerun.exe"):  # fmt: skip
            if candidate.is_file():
                return str(candidate)
    program = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")
    if program is None:
        raise UsageError('occkit view --serve needs the rerun program, an optional extra: pip install -e ".[viewer]"')
    return program


def start_server(bind: str, web_port: int, grpc_port: int, memory_limit: str = "25%",
                 timeout: float = 30.0) -> ViewerServer:  # fmt: skip
    """Start rerun's web viewer and gRPC proxy listening on ``bind`` only, and wait until both ports answer.

    Raises:
        UsageError: a port is taken, or the server did not start (its last words in the message).
    """
    check_port_free(bind, web_port, "--web-port")
    check_port_free(bind, grpc_port, "--grpc-port")
    command = [_rerun_program(), "--serve-web", "--bind", bind, "--port", str(grpc_port), "--web-viewer-port",
               str(web_port), "--server-memory-limit", memory_limit]  # fmt: skip
    log = tempfile.TemporaryFile()  # noqa: SIM115 - open as long as the server runs; ViewerServer.stop closes it
    process = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT)
    server = ViewerServer(process, log, bind, web_port, grpc_port)
    deadline = time.monotonic() + timeout
    connect_to = "127.0.0.1" if bind in ("0.0.0.0", "localhost") else ("::1" if bind == "::" else bind)  # noqa: S104
    while not all(_answers(connect_to, port) for port in (web_port, grpc_port)):
        if process.poll() is not None or time.monotonic() > deadline:
            last = server.last_words()
            server.stop()
            raise UsageError(f"the rerun server on {bind} (ports {web_port}, {grpc_port}) did not start: {last}")
        time.sleep(0.1)
    return server


def _answers(address: str, port: int) -> bool:
    try:
        with socket.create_connection((address, port), timeout=0.5):
            return True
    except OSError:
        return False
