"""Deployment: the Dockerfile installs and starts what README documents; the health probe works.

The image cannot be built here (no container registry is reachable), so the test holds the
Dockerfile and README's "Deployment" section to the same commands.
"""

from __future__ import annotations

import json
import re
import socket
from pathlib import Path

from graph.ascii import parse_ascii_map
from mapmatch.healthcheck import check, main
from service.config import ServerConfig
from service.server import start_server

ROOT = Path(__file__).resolve().parents[1]


def _dockerfile() -> list[str]:
    """Instructions of the Dockerfile, continuation lines joined."""
    text = (ROOT / "Dockerfile").read_text()
    lines = [ln for ln in text.splitlines() if not ln.lstrip().startswith("#")]
    return [ln.strip() for ln in re.sub(r"\\\n\s*", " ", "\n".join(lines)).splitlines() if ln.strip()]


def _readme_deployment() -> str:
    text = (ROOT / "README.md").read_text()
    return text.split("## Deployment", 1)[1].split("\n## ", 1)[0]


def test_dockerfile_installs_and_starts_what_readme_documents() -> None:
    ins = _dockerfile()
    stages = [i for i in ins if i.startswith("FROM ")]
    assert len(stages) >= 2, "multi-stage"
    assert any(i.startswith("USER ") and "root" not in i for i in ins), "non-root"
    # every stage on the base image pinned by digest; versions from the constraints file
    base = next(i for i in ins if i.startswith("ARG BASE="))
    assert re.fullmatch(r"ARG BASE=python:3\.11-slim@sha256:[0-9a-f]{64}", base), base
    assert all(i.split()[1] == "${BASE}" for i in stages), stages
    docs = _readme_deployment()
    # install: the one pip command of the build stage, as README gives it
    pip = [i for i in ins if i.startswith("RUN ") and "pip install" in i]
    assert len(pip) == 1
    install = "pip install " + pip[0].split("pip install ", 1)[1].strip()
    assert install in docs, install
    assert "-c requirements/constraints.txt" in install and (ROOT / "requirements/constraints.txt").is_file()
    # start: ENTRYPOINT + CMD
    entry = json.loads(next(i for i in ins if i.startswith("ENTRYPOINT "))[len("ENTRYPOINT ") :])
    cmd = json.loads(next(i for i in ins if i.startswith("CMD "))[len("CMD ") :])
    start = " ".join(entry + cmd)
    assert start == "mapmatch serve" and f"`{start}`" in docs
    # the address and log format the image sets are documented
    env = " ".join(i for i in ins if i.startswith("ENV "))
    for var in ("MAPMATCH_ADDRESS=0.0.0.0:50051", "MAPMATCH_LOG_FORMAT=json"):
        assert var in env and var in docs
    # health through grpc.health.v1, with the command README names
    hc = next(i for i in ins if i.startswith("HEALTHCHECK "))
    probe = " ".join(json.loads(hc.split(" CMD ", 1)[1]))
    assert probe == "python -m mapmatch.healthcheck 127.0.0.1:50051" and probe in docs
    # the build and run commands in the Dockerfile's header are README's
    header = (ROOT / "Dockerfile").read_text()
    for line in ("docker build -t mapmatch .", "docker run -p 50051:50051"):
        assert line in header and line in docs


def test_health_probe_against_a_real_server() -> None:
    m = parse_ascii_map("a-----------b-----------c", scale=10)
    server, port = start_server(ServerConfig(address="127.0.0.1:0"), {"city": m.graph})
    try:
        assert check(f"127.0.0.1:{port}") == (0, f"127.0.0.1:{port}: SERVING")
        assert main([f"127.0.0.1:{port}"]) == 0
        status, line = check(f"127.0.0.1:{port}", "no.such.Service")
        assert status == 1 and "NOT_FOUND" in line
    finally:
        server.stop(grace=0.5)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        free = s.getsockname()[1]
    status, line = check(f"127.0.0.1:{free}", timeout=1.0)
    assert status == 3 and ("UNAVAILABLE" in line or "DEADLINE_EXCEEDED" in line)
