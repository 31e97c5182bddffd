"""deploy/compose.yaml: the fleet it describes is the one the Dockerfile builds and the failover
test runs (no container engine here: the file is checked, the nginx template it mounts is run by
tests/test_failover.py)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from failover_util import NGINX_TEMPLATE, render_nginx

from service.config import ServerConfig

yaml = pytest.importorskip("yaml")

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = ROOT / "deploy" / "compose.yaml"


def _compose() -> dict:  # type: ignore[type-arg]
    return yaml.safe_load(COMPOSE.read_text())


def _image_port() -> int:
    """The port the Dockerfile's image listens on (MAPMATCH_ADDRESS)."""
    m = re.search(r"MAPMATCH_ADDRESS=[\d.]+:(\d+)", (ROOT / "Dockerfile").read_text())
    assert m, "the Dockerfile sets MAPMATCH_ADDRESS"
    return int(m.group(1))


def test_compose_runs_replicas_of_the_image_behind_nginx_with_redis() -> None:
    services = _compose()["services"]
    servers = {k: v for k, v in services.items() if k.startswith("mapmatch-")}
    assert len(servers) >= 2 and {"redis", "nginx"} <= set(services)
    port = _image_port()
    for name, svc in servers.items():
        assert (COMPOSE.parent / svc["build"]["context"] / "Dockerfile").is_file(), name
        env = {k: str(v) for k, v in svc["environment"].items()}
        # every setting is one the server reads, and each value passes its checks
        cfg = ServerConfig(
            session_store=env["MAPMATCH_SESSION_STORE"],
            checkpoint_interval=float(env["MAPMATCH_CHECKPOINT_INTERVAL"]),
            session_ttl=float(env["MAPMATCH_SESSION_TTL"]),
            grace=float(env["MAPMATCH_GRACE"]),
        )
        assert cfg.session_store is not None and cfg.session_store.startswith("redis://redis:")
        assert "MAPMATCH_MAPS" in env and any(v.endswith(":ro") for v in svc["volumes"])
        # a stop waits for the drain (grace) and the last checkpoint before the kill
        assert float(svc["stop_grace_period"].rstrip("s")) > cfg.grace
        assert svc["depends_on"]["redis"]["condition"] == "service_healthy"
    # nginx mounts the template the failover test runs, and lists every server at the image's port
    ng = services["nginx"]
    mount = next(v for v in ng["volumes"] if "nginx" in v.split(":")[0])
    assert (COMPOSE.parent / mount.split(":")[0]).resolve() == NGINX_TEMPLATE.resolve()
    assert mount.split(":")[1].startswith("/etc/nginx/templates/") and mount.split(":")[1].endswith(
        ".template"
    )
    listed = re.findall(r"server ([\w-]+):(\d+)", ng["environment"]["MAPMATCH_UPSTREAM_SERVERS"])
    assert sorted(listed) == sorted((name, str(port)) for name in servers)
    listen = ng["environment"]["MAPMATCH_LISTEN"]
    assert any(p.split(":")[0] == listen.rsplit(":", 1)[1] for p in ng["ports"])
    # the template holds only these settings, and with them it is the tested configuration
    names = set(re.findall(r"\$\{(MAPMATCH_[A-Z_]+)\}", NGINX_TEMPLATE.read_text()))
    assert names == {k for k in ng["environment"] if k.startswith("MAPMATCH_")}
    assert re.search(r"^\s*\^?MAPMATCH_", ng["environment"]["NGINX_ENVSUBST_FILTER"])


def test_the_template_hashes_on_the_vehicle_header() -> None:
    text = render_nginx(NGINX_TEMPLATE.read_text(), listen=50051, servers=["a:1", "b:2"])
    assert "hash $http_x_vehicle_id consistent;" in text
    assert "grpc_pass grpc://mapmatch;" in text
    assert "server a:1 max_fails=1 fail_timeout=10s; server b:2 max_fails=1 fail_timeout=10s;" in text
