# Two images from one file:
#   target `api`    - the FastAPI service (never imports torch or `worker`; CPU wheels keep it small)
#   target `worker` - Celery GPU worker: CUDA toolkit for gsplat's kernels, CUDA torch,
#                     g++ for fluidcore's fused CPU kernels (no `api` package)
# Both carry `service`, the core they share (settings, database, storage, job types, queue).
# Build: docker compose build   (or docker build --target worker -t fluidnexus-worker .)

ARG PYTHON_IMAGE=python:3.11-slim-bookworm
ARG CUDA_IMAGE=nvidia/cuda:12.8.1-cudnn-devel-ubuntu22.04

FROM ${PYTHON_IMAGE} AS api
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1
WORKDIR /app
COPY pyproject.toml constraints.txt README.md alembic.ini ./
COPY fluidcore fluidcore
COPY fluidnexus fluidnexus
COPY service service
COPY api api
COPY bench bench
COPY migrations migrations
COPY web web
# Editable install: the service finds alembic.ini, migrations/ and web/ next to its packages.
RUN pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu \
 && pip install -c constraints.txt -e .
ENV FLUIDNEXUS_DATA_DIR=/data
EXPOSE 8000
# Runs `alembic upgrade head`, then serves; workers run in their own containers.
CMD ["fluidnexus", "serve", "--host", "0.0.0.0", "--port", "8000", "--no-worker"]

FROM ${CUDA_IMAGE} AS worker
ARG TORCH_INDEX=https://download.pytorch.org/whl/cu128
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 DEBIAN_FRONTEND=noninteractive
RUN apt-get update \
 && apt-get install -y --no-install-recommends python3.11 python3.11-venv python3-pip g++ \
 && rm -rf /var/lib/apt/lists/* \
 && python3.11 -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH
WORKDIR /app
COPY pyproject.toml constraints.txt README.md alembic.ini ./
COPY fluidcore fluidcore
COPY fluidnexus fluidnexus
COPY service service
COPY worker worker
COPY bench bench
COPY migrations migrations
RUN pip install torch==2.13.0 --index-url ${TORCH_INDEX} \
 && pip install -c constraints.txt -e . \
 && python -m fluidcore.kernels build
ENV FLUIDNEXUS_DATA_DIR=/data
# One worker process per GPU, one job at a time (set CUDA_VISIBLE_DEVICES per container).
CMD ["celery", "-A", "worker.tasks", "worker", "--queues", "gpu", "--concurrency", "1", "--loglevel", "INFO"]
