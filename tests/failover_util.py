"""Real Redis and nginx for the fleet tests: each started on a free loopback port in a
temporary folder, and stopped (the test skips, naming the package, when one is not installed)."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NGINX_TEMPLATE = ROOT / "deploy" / "nginx" / "mapmatch-grpc.conf.template"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _need(program: str, package: str) -> str:
    exe = shutil.which(program) or next(
        (str(p) for p in (Path("/usr/sbin") / program, Path("/usr/bin") / program) if p.is_file()), None
    )
    if exe is None:
        pytest.skip(f"needs {program}: apt-get install {package} (.ci/run installs it)")
    return exe


def _wait_port(port: int, proc: subprocess.Popen[bytes], what: str, timeout: float = 15.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if proc.poll() is not None:
            raise RuntimeError(f"{what} ended at start-up (exit status {proc.returncode})")
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), timeout=0.2):
            return
        time.sleep(0.05)
    raise RuntimeError(f"{what} did not listen on port {port} within {timeout} s")


def _stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@contextlib.contextmanager
def redis_server(folder: Path, port: int | None = None) -> Iterator[int]:
    """``redis-server`` on a loopback port (a free one by default), no persistence; yields
    the port."""
    exe = _need("redis-server", "redis-server")
    port = port or free_port()
    folder.mkdir(parents=True, exist_ok=True)
    cmd = [exe, "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
           "--dir", str(folder), "--logfile", str(folder / "redis.log")]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        _wait_port(port, proc, "redis-server")
        yield port
    finally:
        _stop(proc)


def render_nginx(template: str, *, listen: int, servers: Sequence[str]) -> str:
    """The deploy template with its ``${MAPMATCH_...}`` settings filled in (as the nginx
    image's envsubst fills them from the environment)."""
    values = {
        "MAPMATCH_LISTEN": f"127.0.0.1:{listen}",
        "MAPMATCH_UPSTREAM_SERVERS": " ".join(f"server {s} max_fails=1 fail_timeout=10s;" for s in servers),
    }
    out = re.sub(r"\$\{(MAPMATCH_[A-Z_]+)\}", lambda m: values[m.group(1)], template)
    assert "${" not in out
    return out


def nginx_conf(folder: Path, *, listen: int, servers: Sequence[str]) -> Path:
    """A whole nginx.conf around the deploy template, everything inside ``folder``."""
    snippet = folder / "mapmatch-grpc.conf"
    snippet.write_text(render_nginx(NGINX_TEMPLATE.read_text(), listen=listen, servers=servers))
    for sub in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi"):
        (folder / sub).mkdir(exist_ok=True)
    user = "user root;\n" if os.geteuid() == 0 else ""
    conf = folder / "nginx.conf"
    conf.write_text(
        f"{user}worker_processes 1;\npid {folder}/nginx.pid;\nerror_log {folder}/error.log warn;\n"
        "events { worker_connections 1024; }\n"
        "http {\n  access_log off;\n"
        f"  client_body_temp_path {folder}/client_body;\n  proxy_temp_path {folder}/proxy;\n"
        f"  fastcgi_temp_path {folder}/fastcgi;\n  uwsgi_temp_path {folder}/uwsgi;\n"
        f"  scgi_temp_path {folder}/scgi;\n  include {snippet};\n}}\n"
    )
    return conf


@contextlib.contextmanager
def nginx(folder: Path, servers: Sequence[str]) -> Iterator[int]:
    """Debian's nginx in front of ``servers`` (``host:port``) with the deploy template; yields
    the port it listens on."""
    exe = _need("nginx", "nginx")
    folder.mkdir(parents=True, exist_ok=True)
    port = free_port()
    conf = nginx_conf(folder, listen=port, servers=servers)
    cmd = [exe, "-p", str(folder), "-c", str(conf), "-e", str(folder / "error.log"), "-g", "daemon off;"]
    check = subprocess.run([*cmd[:-2], "-t"], capture_output=True, text=True)
    assert check.returncode == 0, check.stderr
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        _wait_port(port, proc, "nginx")
        yield port
    finally:
        _stop(proc)
