"""Config, stub generation, `mapmatch serve`/`send` and graceful shutdown (in-process and SIGTERM)."""

from __future__ import annotations

import ast
import filecmp
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from online_helpers import DriveSpec, drive
from service_util import city, local_config, requests, running, stub

from graph.artifact import save_map
from mapmatch.cli import main
from mapmatch.errors import ConfigError
from service import gen_proto
from service.config import ServerConfig, add_arguments, config_from
from service.gen import mapmatch_pb2 as pb
from service.server import start_server

ROOT = Path(__file__).resolve().parents[1]
AMAP = city()


# ---------------------------------------------------------------------------------- stubs
def _serialized_descriptor(pb2: Path) -> bytes:
    """The serialized ``FileDescriptorProto`` a ``*_pb2.py`` registers: what the messages are."""
    for node in ast.walk(ast.parse(pb2.read_text())):
        if isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "AddSerializedFile":
            value = ast.literal_eval(node.args[0])
            assert isinstance(value, bytes)
            return value
    raise AssertionError(f"{pb2} registers no descriptor")


def _definitions(module: Path) -> set[str]:
    """The classes, functions and methods a module defines, and each method's arguments."""
    out: set[str] = set()
    for node in ast.parse(module.read_text()).body:
        if isinstance(node, ast.FunctionDef):
            out.add(f"{node.name}({', '.join(a.arg for a in node.args.args)})")
        elif isinstance(node, ast.ClassDef):
            out.add(node.name)
            for item in node.body:
                if isinstance(item, ast.FunctionDef):
                    out.add(f"{node.name}.{item.name}({', '.join(a.arg for a in item.args.args)})")
    return out


def test_committed_stubs_are_current(tmp_path):
    """The committed stubs define what ``proto/`` says, whichever grpcio-tools made them (the
    generator's version string and layout may differ; the descriptor and the API may not)."""
    made = gen_proto.generate(tmp_path)
    names = {p.name for p in made}
    assert {"mapmatch_pb2.py", "mapmatch_pb2.pyi", "mapmatch_pb2_grpc.py"} <= names
    stale = "stale: run `python -m service.gen_proto`"
    for rel in made:
        assert (gen_proto.GEN_DIR / rel).is_file(), f"{rel} missing: run `python -m service.gen_proto`"
    for name in names:
        committed, fresh = gen_proto.GEN_DIR / name, tmp_path / name
        if name.endswith("_pb2.py"):
            assert _serialized_descriptor(committed) == _serialized_descriptor(fresh), f"{name} {stale}"
        elif name.endswith((".pyi", "_grpc.py")):
            assert _definitions(committed) == _definitions(fresh), f"{name} {stale}"
    assert _definitions(gen_proto.GEN_DIR / "mapmatch_pb2_grpc.py"), "no stubs parsed"


# ---------------------------------------------------------------------------------- config
def test_config_flags_override_environment_over_defaults(tmp_path):
    import argparse

    p = argparse.ArgumentParser()
    add_arguments(p)
    env = {
        "MAPMATCH_ADDRESS": "0.0.0.0:6000",
        "MAPMATCH_MAPS": "hel=/maps/helsinki.map,mco=/maps/monaco.map",
        "MAPMATCH_SESSION_TTL": "30",
        "MAPMATCH_MAX_SESSIONS": "7",
        "MAPMATCH_REUSE_PORT": "off",
        "MAPMATCH_TOKEN": "from-env",
    }
    c = config_from(p.parse_args([]), env)
    assert c.address == "0.0.0.0:6000" and c.session_ttl == 30.0 and c.max_sessions == 7
    assert c.maps == (("hel", Path("/maps/helsinki.map")), ("mco", Path("/maps/monaco.map")))
    assert c.reuse_port is False and c.token == "from-env"
    (tmp_path / "tok").write_text("from-file\n")
    args = p.parse_args(["--address", "127.0.0.1:7000", "--map", "x=/a.map", "--max-sessions", "9",
                         "--reuse-port", "--workers", "3"])  # fmt: skip
    c = config_from(args, {**env, "MAPMATCH_TOKEN": "", "MAPMATCH_TOKEN_FILE": str(tmp_path / "tok")})
    assert (c.address, c.maps, c.max_sessions, c.reuse_port, c.workers) == (
        "127.0.0.1:7000", (("x", Path("/a.map")),), 9, True, 3
    )  # fmt: skip
    assert c.token == "from-file" and "from-file" not in repr(c)
    d = config_from(p.parse_args([]), {})
    assert d == ServerConfig() and d.address.startswith("127.0.0.1:") and not d.tls and d.token is None
    for bad in ({"MAPMATCH_SESSION_TTL": "soon"}, {"MAPMATCH_MAPS": "=x"}, {"MAPMATCH_LOG_FORMAT": "xml"},
                {"MAPMATCH_REUSE_PORT": "maybe"}, {"MAPMATCH_MAPS": "a=1,a=2"}):  # fmt: skip
        with pytest.raises(ConfigError):
            config_from(p.parse_args([]), bad)


def test_unbindable_address_is_a_config_error():
    with (
        running(local_config(), {"city": AMAP.graph}) as (_, port),
        pytest.raises(ConfigError, match="cannot listen"),
    ):
        start_server(local_config(address=f"127.0.0.1:{port}"), {"city": AMAP.graph})


# ---------------------------------------------------------------------------------- shutdown
def test_graceful_shutdown_drains_in_flight_calls_and_refuses_new_ones():
    server_ctx = running(local_config(grace=5.0), {"city": AMAP.graph})
    server, port = server_ctx.__enter__()
    try:
        ch, api = stub(port)
        health = health_pb2_grpc.HealthStub(ch)
        watch = health.Watch(health_pb2.HealthCheckRequest(service=""), timeout=30)
        assert next(watch).status == health_pb2.HealthCheckResponse.SERVING
        reqs = requests(drive(AMAP, "abc"), "drain")
        feed: queue.Queue = queue.Queue()
        for r in reqs[:5]:
            feed.put(r)
        call = api.StreamFixes(iter(feed.get, None), timeout=30)
        got = [next(call) for _ in range(5)]
        stopper = threading.Thread(target=server.stop)
        stopper.start()
        assert next(watch).status == health_pb2.HealthCheckResponse.NOT_SERVING
        watch.cancel()
        time.sleep(0.3)
        ch2, api2 = stub(port)
        with pytest.raises(grpc.RpcError) as ei:
            api2.ListMaps(pb.ListMapsRequest(), timeout=2)
        assert ei.value.code() == grpc.StatusCode.UNAVAILABLE
        ch2.close()
        for r in reqs[5:]:  # the in-flight stream still gets every answer
            feed.put(r)
        feed.put(None)
        got += list(call)
        assert [g.seq for g in got] == [r.seq for r in reqs] and not any(g.HasField("error") for g in got)
        stopper.join(10)
        assert not stopper.is_alive() and server.wait_for_termination(0)
        ch.close()
    finally:
        server.stop(0)


def _serve_process(tmp_path: Path, *extra: str) -> tuple[subprocess.Popen, int]:
    path = tmp_path / "city.map"
    save_map(AMAP.graph, path)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MAPMATCH_GRACE": "10"}
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "mapmatch",
            "serve",
            "--map",
            f"city={path}",
            "--address",
            "127.0.0.1:0",
            *extra,
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        cwd=ROOT,
    )
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if "listening on" not in line:
        proc.kill()
        raise AssertionError(f"server did not start: {line!r} {proc.stderr.read() if proc.stderr else ''}")
    return proc, int(line.split("listening on ")[1].split()[0].rsplit(":", 1)[1])


@pytest.mark.slow  # a server process and its grace period
def test_sigterm_shuts_down_gracefully(tmp_path):
    proc, port = _serve_process(tmp_path)
    try:
        ch, api = stub(port)
        reqs = requests(drive(AMAP, "abc"), "sigterm")
        feed: queue.Queue = queue.Queue()
        for r in reqs[:3]:
            feed.put(r)
        call = api.StreamFixes(iter(feed.get, None), timeout=30)
        got = [next(call) for _ in range(3)]
        proc.send_signal(signal.SIGTERM)
        time.sleep(0.5)
        assert proc.poll() is None  # still draining the open stream
        for r in reqs[3:]:
            feed.put(r)
        feed.put(None)
        got += list(call)
        assert len(got) == len(reqs) and not any(g.HasField("error") for g in got)
        assert proc.wait(15) == 0
        ch.close()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.slow  # several server processes on one port
def test_processes_share_one_port_each_with_its_own_sessions(tmp_path):
    proc, port = _serve_process(tmp_path, "--processes", "2")
    try:
        assert proc.stdout is not None
        assert "2 server processes" in proc.stdout.readline()
        servers: dict[str, list[pb.SnapResponse]] = {}
        reqs = requests(drive(AMAP, "abc"), "multi")
        # one TCP connection each: the kernel spreads them over the processes (the second may
        # still be starting on a loaded machine, so keep connecting until both have answered)
        for i in range(48):
            if len(servers) == 2 and i >= 12:
                break
            ch, api = stub(port, options=[("grpc.use_local_subchannel_pool", 1)])
            sid = api.ListMaps(pb.ListMapsRequest(), timeout=10).server_id
            got = list(api.StreamFixes(iter(requests(drive(AMAP, "abc"), f"v{i}")), timeout=30))
            assert len(got) == len(reqs) and not any(g.HasField("error") for g in got)
            servers.setdefault(sid, []).extend(got)
            ch.close()
        assert len(servers) == 2, servers.keys()  # both processes served (1 in 2**47 to fail by chance)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.slow  # server processes with batch workers
def test_a_second_server_on_a_port_in_use_exits_3_also_with_processes(tmp_path):
    proc, port = _serve_process(tmp_path)
    try:
        path = tmp_path / "city.map"
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        cmd = [sys.executable, "-m", "mapmatch", "serve", "--map", f"city={path}",
               "--address", f"127.0.0.1:{port}", "--processes", "2"]  # fmt: skip
        out = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT, timeout=60)
        assert out.returncode == 3
        assert "address already in use" in out.stderr.strip().splitlines()[-1]
    finally:
        proc.kill()
        proc.wait()


# ---------------------------------------------------------------------------------- send
def _fixes_csv(path: Path) -> None:
    lines = ["vehicle_id,time,lat,lon,heading,pos_sigma,speed,distance,gps_valid"]
    for vid, route in (("car-1", "abcf"), ("car-2", "gdab")):
        for f in drive(AMAP, route, DriveSpec(speed=10.0, dt=1.0, noise=1.0, seed=len(vid), sigma=3.0)):
            lines.append(f"{vid},{f.time},{f.lat:.8f},{f.lon:.8f},{f.heading:.2f},3.0,{f.speed},10.0,1")
    lines.append("car-1,1000,95.0,24.9,90,3.0,10,10,1")  # a bad fix: rejected, reported
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.slow  # a real server, send and replay processes
def test_send_writes_the_same_rows_as_replay(tmp_path, capsys):
    fixes = tmp_path / "fixes.csv"
    _fixes_csv(fixes)
    proc, port = _serve_process(tmp_path)
    try:
        out = tmp_path / "sent.csv"
        assert main(["send", "--server", f"127.0.0.1:{port}", str(fixes), "-o", str(out)]) == 1  # 1 rejected
        assert "matched by" in capsys.readouterr().out
        ref = tmp_path / "replayed.csv"
        assert main(["replay", "--map", str(tmp_path / "city.map"), str(fixes), "-o", str(ref)]) == 1
        assert out.read_text().count("\n") == fixes.read_text().count("\n")
        assert filecmp.cmp(out, ref, shallow=False), "send and replay disagree"
        assert ",rejected," in out.read_text()
    finally:
        proc.terminate()
        proc.wait(15)


def test_send_errors_are_one_line(tmp_path, capsys):
    fixes = tmp_path / "fixes.csv"
    _fixes_csv(fixes)
    # nothing listens on this port (bound, then released)
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    code = main(
        ["send", "--server", f"127.0.0.1:{port}", "--timeout", "2", str(fixes), "-o", str(tmp_path / "o.csv")]
    )
    err = capsys.readouterr().err
    assert code == 3 and err.count("\n") == 1 and "UNAVAILABLE" in err
    assert not (tmp_path / "o.csv").exists()
    assert main(["send", str(tmp_path / "missing.csv"), "-o", str(tmp_path / "o.csv")]) != 0
