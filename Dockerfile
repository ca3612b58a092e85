# One image for every service of the cluster (docker-compose.yml picks the command).
FROM python:3.11-slim
WORKDIR /app
# torch is pinned to the CPU build the project uses; pass a CPU-only package index
# with --build-arg TORCH_PIP_ARGS="--index-url ..." to avoid the large CUDA wheels.
ARG TORCH_PIP_ARGS=""
RUN pip install --no-cache-dir torch==2.13.0 ${TORCH_PIP_ARGS}
COPY pyproject.toml README.md ./
COPY shared shared
COPY services services
COPY cli cli
COPY configs configs
RUN pip install --no-cache-dir .
ENV PYTHONUNBUFFERED=1
VOLUME /data
CMD ["macb", "--help"]
