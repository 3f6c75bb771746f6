# pitune: the tuner daemon, the plant simulator and the demo, CPU only.
#   docker build -t pitune:local .
#   docker run --rm -p 127.0.0.1:8750:8750 -e PITUNE_API_TOKEN="$(openssl rand -hex 32)" \
#     pitune:local tuner    # the API on this host only; the compose deployment: docs/deploy.md
# Build arguments (all optional; docs/deploy.md, "Building the image"):
#   PYTHON_IMAGE     runtime base (python:3.11-slim-bookworm)
#   BUILD_IMAGE      build-stage base, the same Python at the same path (the same image, or
#                    one with gcc already in it: then apt-get is not needed)
#   INDEX_URL        a PyPI mirror for the dependencies (default: pypi.org, or none at all
#                    when deploy/wheelhouse/ holds wheels: an offline build)
#   TORCH_INDEX_URL  where the CPU build of torch comes from when the wheelhouse has none
# deploy/wheelhouse/ (made by deploy/wheelhouse.sh) is used when it holds wheels;
# deploy/constraints.txt pins every dependency of the image (reproducible builds).
ARG PYTHON_IMAGE=python:3.11-slim-bookworm
ARG BUILD_IMAGE=python:3.11-slim-bookworm

FROM ${BUILD_IMAGE} AS build
ARG INDEX_URL=
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
ENV PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PIP_CONSTRAINT=/src/constraints.txt \
    PATH=/opt/pitune/bin:$PATH
# A C compiler for service/agent/_gru.c (the GRU step's fused kernel); build stage only,
# from apt unless the build image has one. Any gcc of the release builds it, and a pinned
# version would break at each point release.
# hadolint ignore=DL3008
RUN if ! command -v gcc >/dev/null; then \
        apt-get update \
        && apt-get install -y --no-install-recommends gcc libc6-dev \
        && rm -rf /var/lib/apt/lists/*; \
    fi
WORKDIR /src
COPY deploy/constraints.txt ./
COPY deploy/wheelhouse /wheelhouse
# Where packages come from: the wheelhouse alone (offline) if it holds wheels and no
# INDEX_URL is given; otherwise the index (INDEX_URL or pypi.org), plus the wheelhouse.
# The CPU build of torch first: `pip install .` then finds torch satisfied and never
# pulls the CUDA build. Versions: PIP_CONSTRAINT (deploy/constraints.txt).
# hadolint ignore=SC2086,DL3013
RUN set -eu; \
    python -m venv /opt/pitune; \
    links=; index=; \
    if ls /wheelhouse/*.whl >/dev/null 2>&1; then links="--find-links /wheelhouse"; fi; \
    if [ -n "$INDEX_URL" ]; then index="--index-url $INDEX_URL"; \
    elif [ -n "$links" ]; then index=--no-index; fi; \
    if ls /wheelhouse/torch-*.whl >/dev/null 2>&1; then torch_index=$index; \
    else torch_index="--index-url $TORCH_INDEX_URL"; fi; \
    echo "pip sources: ${links:-no wheelhouse} ${index:-pypi.org}; torch: $torch_index" ; \
    pip install $links $torch_index torch==2.13.0; \
    echo "$links $index" > /src/pip-sources
# Then every pinned dependency, in a layer of its own that a change of pitune's code does
# not invalidate (`pip install .` below only adds pitune).
# hadolint ignore=SC2046,DL3013
RUN pip install $(cat /src/pip-sources) --requirement /src/constraints.txt
COPY pyproject.toml README.md ./
COPY service ./service
COPY plant_sim ./plant_sim
# hadolint ignore=SC2046,DL3013
RUN pip install $(cat /src/pip-sources) . \
    && pip check

FROM ${PYTHON_IMAGE}
RUN useradd --create-home --uid 10001 --shell /usr/sbin/nologin pitune \
    && mkdir /data \
    && chown pitune:pitune /data
COPY --from=build /opt/pitune /opt/pitune
ENV PATH=/opt/pitune/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    MPLBACKEND=Agg \
    PITUNE_API_HOST=0.0.0.0 \
    PITUNE_API_PORT=8750 \
    PITUNE_DB_PATH=/data/pitune.db
USER 10001:10001
WORKDIR /data
VOLUME ["/data"]
EXPOSE 8750
# The plant simulator and the router stand-in run from this image too; compose disables
# the check for them. Podman 4.3 runs it only through systemd timers (`podman
# healthcheck run` by hand otherwise); nothing in the deployment depends on it.
HEALTHCHECK --interval=15s --timeout=5s --start-period=60s --retries=3 \
    CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:%s/healthz' % os.environ.get('PITUNE_API_PORT', '8750'), timeout=4)"]
ENTRYPOINT ["pitune"]
CMD ["tuner"]
