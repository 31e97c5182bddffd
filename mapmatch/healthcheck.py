"""``python -m mapmatch.healthcheck [HOST:PORT] [SERVICE]``: ask a server's gRPC health service.

Exit status 0 when the server answers SERVING, 1 when it answers anything else, 3 when it
cannot be reached within ``--timeout``: what a container health check (Dockerfile
``HEALTHCHECK``) or a load balancer's probe script needs. SERVICE defaults to "" (the whole
server).
"""

from __future__ import annotations

import argparse
import sys


def check(address: str, service: str = "", *, timeout: float = 3.0) -> tuple[int, str]:
    """``(exit status, one-line answer)`` of the health service at ``address``."""
    import grpc
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    with grpc.insecure_channel(address) as channel:
        try:
            resp = health_pb2_grpc.HealthStub(channel).Check(
                health_pb2.HealthCheckRequest(service=service), timeout=timeout
            )
        except grpc.RpcError as exc:
            code = exc.code()
            status = 1 if code is grpc.StatusCode.NOT_FOUND else 3
            return status, f"{address}: {code.name}: {exc.details()}"
    name = health_pb2.HealthCheckResponse.ServingStatus.Name(resp.status)
    return (0 if name == "SERVING" else 1), f"{address}: {name}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m mapmatch.healthcheck", description=__doc__.split("\n")[0])
    p.add_argument("address", nargs="?", default="127.0.0.1:50051", help="HOST:PORT (127.0.0.1:50051)")
    p.add_argument("service", nargs="?", default="", help="service name (default: the whole server)")
    p.add_argument("--timeout", type=float, default=3.0, help="seconds (3)")
    args = p.parse_args(argv)
    status, line = check(args.address, args.service, timeout=args.timeout)
    print(line, file=sys.stdout if status == 0 else sys.stderr)
    return status


if __name__ == "__main__":
    sys.exit(main())
