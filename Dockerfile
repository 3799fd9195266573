# syntax=docker/dockerfile:1
# The ComplementMe suggestion service: onnxruntime + FAISS behind uvicorn, no torch.
#
#   docker build -t complementme:0.1.0 .
#   docker run --rm -p 8000:8000 complementme:0.1.0
#
# Settings are COMPLEMENTME_* environment variables (docs/settings.md). The container runs one
# server process; keep COMPLEMENTME_ONNX_THREADS (and COMPLEMENTME_FAISS_THREADS) at or below
# the CPU cores it may use, and scale by containers (docs/deploy.md).
#
# tests/deploy/test_image_steps.py runs this file's RUN steps and its CMD in a fresh virtual
# environment (no container engine is needed): keep every RUN step free of absolute paths
# except through $VIRTUAL_ENV, and keep system steps (user creation) in the one RUN that starts
# with `groupadd`.

# --- stage 1: the service's dependencies, at the versions CI tested (docker/constraints.txt),
# cached until docker/requirements-service.txt or docker/constraints.txt changes
FROM python:3.11-slim AS deps
ENV VIRTUAL_ENV=/opt/venv \
    PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /build
COPY docker/requirements-service.txt docker/constraints.txt docker/
RUN --mount=type=cache,target=/root/.cache/pip \
    python -m venv "$VIRTUAL_ENV" \
    && "$VIRTUAL_ENV/bin/pip" install -r docker/requirements-service.txt -c docker/constraints.txt

# --- stage 2: a wheel of the project's code (the `service`, `training` and `complementme_client`
# packages; training imports torch only inside its commands, and torch is not installed in the image)
FROM python:3.11-slim AS wheel
ENV PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /build
COPY pyproject.toml README.md LICENSE ./
COPY service/ service/
COPY training/ training/
COPY clients/python/complementme_client/ clients/python/complementme_client/
RUN --mount=type=cache,target=/root/.cache/pip \
    python -m pip wheel --no-deps --wheel-dir dist .

# --- stage 3: the image. Layers from the least to the most often changed: dependencies, then
# the trained artifacts, then the code, so a code edit neither reinstalls nor re-copies them.
FROM python:3.11-slim AS runtime
ENV VIRTUAL_ENV=/opt/venv \
    PATH="/opt/venv/bin:$PATH" \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    OMP_NUM_THREADS=1 \
    OPENBLAS_NUM_THREADS=1 \
    COMPLEMENTME_ARTIFACTS=/app/exported \
    COMPLEMENTME_DATA_DIR=/data \
    COMPLEMENTME_HOST=0.0.0.0 \
    COMPLEMENTME_PORT=8000 \
    COMPLEMENTME_ONNX_THREADS=1 \
    COMPLEMENTME_FAISS_THREADS=1
RUN groupadd --system --gid 10001 app \
    && useradd --system --no-log-init --uid 10001 --gid app --create-home --home-dir /home/app app \
    && install -d -o app -g app /data
WORKDIR /app
COPY --from=deps /opt/venv /opt/venv
COPY exported/ exported/
COPY docker/healthcheck.py healthcheck.py
COPY --from=wheel /build/dist/ dist/
# The compiled kernels (contact refinement's search and the assembly's cover shares, the OBJ reader,
# the suggestion order's spread) are compiled by numba on first use (about 30 s): compile them here,
# into the installed package's __pycache__, so a container loads them from that cache instead.
RUN pip install --no-cache-dir --no-deps dist/*.whl \
    && rm -rf dist \
    && python -m service.suggest.contact_kernel \
    && python -m service.geometry.mesh_kernel \
    && python -m service.suggest.spread_kernel
USER 10001:10001
EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s --retries=3 \
    CMD ["python", "/app/healthcheck.py"]
CMD ["complementme", "serve"]
