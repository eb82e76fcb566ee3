# A GPU inference node: a Ray worker node with the machine's GPU (docker/compose.yaml, profile "gpu"). The
# same install as the service image, without the CPU wheel index: PyPI's torch==2.13.0 for Linux is the
# CUDA build, which brings its own CUDA runtime; the host gives the driver (NVIDIA Container Toolkit).
FROM python:3.11-slim-bookworm

RUN apt-get update \
    && apt-get install -y --no-install-recommends make libgl1 libglib2.0-0 \
    && rm -rf /var/lib/apt/lists/*

WORKDIR /app
COPY . .
ENV PIP_NO_CACHE_DIR=1 \
    PYTHONUNBUFFERED=1
RUN make install EXTRAS=postgres,ray

ENTRYPOINT ["docker/entrypoint.sh"]
CMD [".venv/bin/ray", "start", "--address=ray-head:6379", "--num-gpus=1", "--block"]
