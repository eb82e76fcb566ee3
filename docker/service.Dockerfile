# The fleet service on CPU: the API, the control loop and the nightly job; the same image runs the Ray head
# and the CPU Ray workers (docker/compose.yaml). It installs with the README's command (`make install`), so
# the tested path is the shipped one; PyPI's torch wheel for Linux is the CUDA build, so this image takes
# PyTorch's CPU wheel of the same pinned version.
FROM python:3.11-slim-bookworm

# make runs the install; robosuite's OpenCV needs libGL and GLib even without a screen
RUN apt-get update \
    && apt-get install -y --no-install-recommends make libgl1 libglib2.0-0 \
    && rm -rf /var/lib/apt/lists/*

WORKDIR /app
COPY . .
ENV PIP_EXTRA_INDEX_URL=https://download.pytorch.org/whl/cpu \
    PIP_NO_CACHE_DIR=1 \
    PYTHONUNBUFFERED=1
RUN make install EXTRAS=postgres,ray

EXPOSE 8000
ENTRYPOINT ["docker/entrypoint.sh"]
CMD [".venv/bin/hitl", "serve", "--host", "0.0.0.0", "--config", "configs/compose.toml"]
