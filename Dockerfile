# One image for every service of the cluster (docker-compose.yml picks the command).
# The defaults are for a machine that reaches Docker Hub and download.pytorch.org:
#   docker build -t macb:latest .
# Without a registry (README, "Containers without a registry"), docker/offline.py
# passes a debootstrap base and the local torch wheel:
#   --build-arg BASE_IMAGE=macb-base:... --build-arg TORCH_SOURCE="--no-index
#   --find-links /tmp/local --no-deps" --build-arg PIP_CA=ca-certificates.crt
# Every pin comes from pyproject.toml, torch's included.

# Any image with python3 3.11 and its venv module.
ARG BASE_IMAGE=python:3.11-slim

FROM ${BASE_IMAGE} AS build
# Where the pinned torch comes from, as pip options: the CPU wheel index by default
# (the CUDA build on PyPI is several GB); offline, a wheel put in docker/local/. For a
# GPU, a CUDA index (the pin matches its build, e.g. 2.13.0+cu128):
#   --build-arg TORCH_SOURCE="--index-url https://download.pytorch.org/whl/cu128"
ARG TORCH_SOURCE="--index-url https://download.pytorch.org/whl/cpu"
# A CA bundle in docker/local/ for pip (for a TLS-inspecting proxy in front of the
# package index); empty: pip's own bundle.
ARG PIP_CA=""
COPY docker/local/ /tmp/local/
COPY pyproject.toml /tmp/pins/
RUN python3 -m venv /opt/macb \
 && /opt/macb/bin/python -c 'import sys, tomllib; deps = tomllib.load(open(sys.argv[1], "rb"))["project"]["dependencies"]; print("\n".join(deps))' /tmp/pins/pyproject.toml > /tmp/pins/requirements.txt \
 && if [ -n "$PIP_CA" ]; then export PIP_CERT="/tmp/local/$PIP_CA"; fi \
 && /opt/macb/bin/pip install --no-cache-dir --disable-pip-version-check ${TORCH_SOURCE} "$(grep '^torch==' /tmp/pins/requirements.txt)" \
 && /opt/macb/bin/pip install --no-cache-dir --disable-pip-version-check -r /tmp/pins/requirements.txt
COPY pyproject.toml README.md /src/
COPY shared /src/shared
COPY services /src/services
COPY cli /src/cli
COPY macb /src/macb
COPY examples /src/examples
# PIP_CERT (not --cert) so that pip's isolated build of the project trusts it too.
RUN if [ -n "$PIP_CA" ]; then export PIP_CERT="/tmp/local/$PIP_CA"; fi \
 && /opt/macb/bin/pip install --no-cache-dir --disable-pip-version-check --no-deps /src

# The venv alone: the wheel, the CA bundle and the sources stay in the build stage.
FROM ${BASE_IMAGE}
COPY --from=build /opt/macb /opt/macb
ENV PATH=/opt/macb/bin:$PATH PYTHONUNBUFFERED=1
WORKDIR /app
COPY configs configs
# (the wheel has no configs/: the figures' arms and the dashboard's presets are read here)
ENV MACB_CONFIGS_DIR=/app/configs
VOLUME /data
CMD ["macb", "--help"]
