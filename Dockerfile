# syntax=docker/dockerfile:1
# One image for every role: `agv-fe serve` (default), `agv-fe fleet`, `agv-fe dashboard`, ...
# Build: docker build -t agv-fe .     Run: docker compose up (see docker-compose.yml)

FROM python:3.11-slim-bookworm AS build
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
RUN python -m venv /opt/agv-fe
# pinned dependencies first: this layer is rebuilt only when requirements.lock changes
COPY requirements.lock /tmp/requirements.lock
RUN /opt/agv-fe/bin/pip install -r /tmp/requirements.lock
WORKDIR /src
COPY pyproject.toml README.md LICENSE ./
COPY synth ./synth
COPY agv_protocol ./agv_protocol
COPY service ./service
COPY edge_client ./edge_client
COPY agv_fe ./agv_fe
RUN /opt/agv-fe/bin/pip install --no-deps . && /opt/agv-fe/bin/agv-fe --help > /dev/null

FROM python:3.11-slim-bookworm
RUN useradd --system --uid 10001 --user-group --create-home --home-dir /home/agv agv \
    && mkdir /data && chown agv:agv /data
COPY --from=build /opt/agv-fe /opt/agv-fe
ENV PATH=/opt/agv-fe/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    MPLCONFIGDIR=/tmp/matplotlib \
    AGV_FE_DATA_DIR=/data \
    AGV_FE_HTTP__HOST=0.0.0.0 \
    AGV_FE_HTTP__PORT=8000
# numeric, so that a runtime refusing to run as root (runAsNonRoot) can check it without reading /etc/passwd
USER 10001:10001
WORKDIR /home/agv
VOLUME ["/data"]
EXPOSE 8000 7447
# the service's health; roles without HTTP (fleet, dashboard) disable it in docker-compose.yml
HEALTHCHECK --interval=10s --timeout=3s --start-period=120s --retries=3 \
    CMD ["python", "-c", "import os, sys, urllib.request; port = os.environ.get('AGV_FE_HTTP__PORT', '8000'); sys.exit(0 if urllib.request.urlopen(f'http://127.0.0.1:{port}/health', timeout=2).status == 200 else 1)"]
ENTRYPOINT ["agv-fe"]
CMD ["serve"]
