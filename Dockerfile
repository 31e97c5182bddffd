# mapmatch gRPC service. Builds from a clone with nothing but pip:
#   docker build -t mapmatch .
#   docker run -p 50051:50051 -v "$PWD/maps:/maps:ro" -e MAPMATCH_MAPS=city=/maps/city.map mapmatch
# (README, "Deployment"). Stage 1 installs the package into a venv; stage 2 copies only that
# venv (the core install with the session store's client and uvloop: no map preparation), runs as an unprivileged user, compiles the batch and online kernels once at build time (so the
# first MatchTrack and the first fixes are fast) and checks health through grpc.health.v1.

# The base image is pinned by digest (the same for both stages): a rebuild gets the same
# Python and Debian. To move it on: `docker buildx imagetools inspect python:3.11-slim` and
# put the index digest here. The package's versions come from requirements/constraints.txt.
ARG BASE=python:3.11-slim@sha256:9c900dea9e8fb7e16277c179b555cc72d29a352dbc33cff48ad5a0412fd5bfc7

FROM ${BASE} AS build
WORKDIR /src
COPY . .
RUN python -m venv /opt/mapmatch \
 && /opt/mapmatch/bin/python -m pip install --no-cache-dir -c requirements/constraints.txt '.[redis,uvloop]'

FROM ${BASE}
RUN useradd --create-home --uid 10001 mapmatch
COPY --from=build --chown=mapmatch:mapmatch /opt/mapmatch /opt/mapmatch
ENV PATH=/opt/mapmatch/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    MAPMATCH_ADDRESS=0.0.0.0:50051 \
    MAPMATCH_LOG_FORMAT=json
USER mapmatch
WORKDIR /home/mapmatch
RUN python -m mapmatch.kernels batch online
EXPOSE 50051
HEALTHCHECK --interval=10s --timeout=5s --start-period=60s --retries=3 \
  CMD ["python", "-m", "mapmatch.healthcheck", "127.0.0.1:50051"]
ENTRYPOINT ["mapmatch"]
CMD ["serve"]
