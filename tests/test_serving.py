"""``occkit view --serve``: rerun's server listens on loopback unless told otherwise; a taken port is one line."""

from __future__ import annotations

import socket
import subprocess
from pathlib import Path

import pytest

from occkit.errors import UsageError
from occkit.viz.serving import check_bind, check_port_free, is_loopback

pytest.importorskip("rerun")


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _listening(port: int) -> list[str]:
    """The local addresses listening on ``port`` (from /proc/net/tcp*, as ``ss -ltn`` reads them)."""
    found = []
    for table, width in (("/proc/net/tcp", 8), ("/proc/net/tcp6", 32)):
        try:
            rows = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for row in rows:
            local, state = row.split()[1], row.split()[3]
            address, port_hex = local.split(":")
            if state == "0A" and int(port_hex, 16) == port:  # 0A: LISTEN
                found.append(address if width == 32 else socket.inet_ntoa(bytes.fromhex(address)[::-1]))
    return found


def test_the_server_listens_on_loopback_only_and_stops():
    from occkit.viz.serving import start_server

    web, grpc = _free_port(), _free_port()
    server = start_server("127.0.0.1", web, grpc)
    try:
        assert _listening(web) == ["127.0.0.1"] and _listening(grpc) == ["127.0.0.1"]
        assert server.web_url.startswith(f"http://127.0.0.1:{web}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc}")
        with pytest.raises(UsageError, match=f"--web-port {web} is already in use on 127.0.0.1"):
            start_server("127.0.0.1", web, _free_port())
    finally:
        server.stop()
    assert server.process.poll() is not None and _listening(web) == [] and _listening(grpc) == []


def test_view_serve_defaults_to_loopback_and_warns_when_opened_wider(capsys):
    from occkit.cli import build_parser

    assert build_parser().parse_args(["view", "--data", ".", "--serve"]).bind == "127.0.0.1"
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.1.5")
    assert check_bind("0.0.0.0") == "0.0.0.0"
    with pytest.raises(UsageError, match="--bind 'everywhere' is not an IP address"):
        check_bind("everywhere")


def test_a_taken_port_is_one_line_naming_it(tmp_path, capsys):
    from occkit.cli import main

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(UsageError, match=f"--grpc-port {port} is already in use"):
            check_port_free("127.0.0.1", port, "--grpc-port")
        (tmp_path / "data").mkdir()
        assert main(["view", "--data", str(tmp_path / "data"), "--serve", "--web-port", str(_free_port()),
                     "--grpc-port", str(port)]) == 2  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"occkit view: error: --grpc-port {port} is already in use on 127.0.0.1: choose another port "
                   "with --grpc-port"]  # fmt: skip
    assert subprocess.run(["pgrep", "-f", f"--port {port}"], capture_output=True).stdout == b""
