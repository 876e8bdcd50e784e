# One image for the three services (docker-compose.yml picks the command).
FROM python:3.11-slim

ENV PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1
WORKDIR /app

# open3d (baseline, mesh ray casting) needs libusb and libgomp at import.
RUN apt-get update && apt-get install -y --no-install-recommends libusb-1.0-0 libgomp1 \
    && rm -rf /var/lib/apt/lists/*

# CPU build of torch by default; for CUDA build with --build-arg TORCH_INDEX=https://download.pytorch.org/whl/cu124
ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu
RUN pip install --index-url ${TORCH_INDEX} "torch>=2.2,<2.14"

COPY pyproject.toml README.md ./
COPY shared ./shared
COPY services ./services
RUN pip install . && aisdf --version && aisdf-mapper --version && aisdf-query --version && aisdf-frontend --version

# Zenoh's default port, for a service that listens.
EXPOSE 7447
CMD ["aisdf", "--help"]
