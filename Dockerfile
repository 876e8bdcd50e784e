# One image for the three services (docker-compose.yml picks the command): the services'
# dependencies only (no benchmark, viewer or test extras), torch's CPU build, and none of
# torch's tests, test binaries or C++ headers. Built in one stage, copied into a fresh one.
FROM python:3.11-slim AS build

ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
RUN apt-get update && apt-get install -y --no-install-recommends binutils && rm -rf /var/lib/apt/lists/*

# torch's CPU build from PyTorch's CPU index; for CUDA: --build-arg TORCH_INDEX=https://download.pytorch.org/whl/cu124.
# Where download.pytorch.org is out of reach, TORCH_FIND_LINKS names a folder or URL (reachable from the build)
# holding a CPU wheel of torch; its dependencies then come from PyPI.
ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu
ARG TORCH_FIND_LINKS=
RUN if [ -n "$TORCH_FIND_LINKS" ]; then \
        pip install --no-compile --no-index --no-deps --find-links "$TORCH_FIND_LINKS" "torch>=2.2,<2.14" \
        && pip install --no-compile "torch>=2.2,<2.14"; \
    else pip install --no-compile --index-url "$TORCH_INDEX" "torch>=2.2,<2.14"; fi

WORKDIR /src
COPY pyproject.toml README.md ./
COPY shared ./shared
COPY services ./services
# No byte code in the image (Python writes it in each container at first import); torch's test
# suite, test binaries, headers and CMake files out; symbols stripped from the two largest libraries.
RUN pip install . --no-compile \
    && cd /usr/local/lib/python3.11/site-packages \
    && rm -rf torch/test torch/include torch/share torch/bin/test_* torch/bin/*Test torch/bin/protoc* \
    && strip --strip-unneeded torch/lib/libtorch_cpu.so llvmlite/binding/libllvmlite.so \
    && find . -name __pycache__ -type d -prune -exec rm -rf {} + \
    && python -c "import torch, sys; sys.exit('torch is not the CPU build' if torch.version.cuda and '${TORCH_INDEX}'.endswith('/cpu') else 0)"

FROM python:3.11-slim
# NUMBA_CACHE_DIR: the baked field's kernels, compiled once below, outside the byte code the
# image leaves out (a new container's first bake and query of a small field: 2.5 s cold, 1.3 s with it, 2 cores).
ENV PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 NUMBA_CACHE_DIR=/var/cache/aisdf-numba
COPY --from=build /usr/local/lib/python3.11/site-packages /usr/local/lib/python3.11/site-packages
COPY --from=build /usr/local/bin/aisdf* /usr/local/bin/
# A smoke test: every command starts; the mapper trains a step and the query service answers from it.
RUN aisdf-mapper --version && aisdf-query --version && aisdf-frontend --version && aisdf-router --version \
    && aisdf-health --help >/dev/null \
    && python -c "import aisdf_mapper.main, aisdf_query.main, aisdf_frontend.main, numpy as np; \
from aisdf.mapper.factory import make_mapper; from aisdf.synthetic import SyntheticSequence; \
from aisdf.mapping.frames import Frame; \
f = SyntheticSequence(building='atlanta', n_frames=10, H=30, W=40).frame(0); \
p = make_mapper('single', 'cpu', {'network': {'width': 16}, 'n_rays': 10}); \
p.add_keyframe(Frame(f['frame_id'], f['stamp'], f['depth'], f['K'], f['T_WC'])); p.step(); \
print('smoke test: trained', p.steps, 'step(s)')" \
    && find /usr/local/lib/python3.11/site-packages -name __pycache__ -type d -prune -exec rm -rf {} +
# The bake's kernels into NUMBA_CACHE_DIR (numba checks the sources' stamps; another CPU recompiles).
RUN python -c "import numpy as np; from aisdf.baked import bake; from aisdf.observed import ObservedGrid; \
occ = np.zeros((4, 4, 4), bool); occ[1:3, 1:3, 1:3] = True; \
f = bake(lambda p: (p[:, 0].copy(), np.tile(np.float32([1, 0, 0]), (len(p), 1))), ObservedGrid(np.zeros(3), 0.1, occ)); \
v = [f.query(np.full((1, 3), 0.15), g)[0][0] for g in (True, False)]; assert abs(v[0] - 0.15) < 1e-6, v; \
print('bake kernels compiled and cached')" \
    && ls /var/cache/aisdf-numba \
    && find /usr/local/lib/python3.11/site-packages -name __pycache__ -type d -prune -exec rm -rf {} +

# Zenoh's default port, for a service that listens.
EXPOSE 7447
CMD ["aisdf-mapper", "--help"]
