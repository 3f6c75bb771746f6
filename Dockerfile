# syntax=docker/dockerfile:1
# pitune: the tuner daemon, the plant simulator and the demo, CPU only.
#   docker build -t pitune:local .
#   docker run --rm -p 127.0.0.1:8750:8750 -e PITUNE_API_TOKEN="$(openssl rand -hex 32)" \
#     pitune:local tuner    # the API on this host only; the compose deployment: docs/deploy.md
ARG PYTHON_IMAGE=python:3.11-slim-bookworm

FROM ${PYTHON_IMAGE} AS build
ENV PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PATH=/opt/pitune/bin:$PATH
# A C compiler for service/_gru.c (the GRU step's fused kernel); build stage only. Any
# gcc of the release builds it, and a pinned version would break at each point release.
# hadolint ignore=DL3008
RUN apt-get update \
    && apt-get install -y --no-install-recommends gcc libc6-dev \
    && rm -rf /var/lib/apt/lists/*
# CPU wheels first: `pip install .` then finds torch satisfied and never pulls CUDA.
RUN python -m venv /opt/pitune \
    && pip install --no-cache-dir torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu
WORKDIR /src
COPY pyproject.toml README.md ./
COPY service ./service
COPY plant_sim ./plant_sim
RUN pip install --no-cache-dir .

FROM ${PYTHON_IMAGE}
RUN useradd --create-home --uid 10001 --shell /usr/sbin/nologin pitune \
    && mkdir /data \
    && chown pitune:pitune /data
COPY --from=build /opt/pitune /opt/pitune
ENV PATH=/opt/pitune/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    MPLBACKEND=Agg \
    PITUNE_API_HOST=0.0.0.0 \
    PITUNE_API_PORT=8750 \
    PITUNE_DB_PATH=/data/pitune.db
USER 10001:10001
WORKDIR /data
VOLUME ["/data"]
EXPOSE 8750
# The plant simulator runs from this image too; compose disables the check for it.
HEALTHCHECK --interval=15s --timeout=5s --start-period=60s --retries=3 \
    CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:%s/healthz' % os.environ.get('PITUNE_API_PORT', '8750'), timeout=4)"]
ENTRYPOINT ["pitune"]
CMD ["tuner"]
