# Stand-in for the official `postgres` image, from Debian bookworm's PostgreSQL 15 (the newest Debian bookworm has;
# the official `postgres:16` cannot be built from Debian packages here, so this image is tagged `postgres:15` and
# docker-compose.yml's POSEMETRY_POSTGRES_IMAGE selects it). build.sh beside this file builds it only where the
# official image can be neither found locally nor pulled.
#
# The official image's contract that docker-compose.yml relies on: POSTGRES_USER, POSTGRES_PASSWORD and
# POSTGRES_DB initialise an empty data directory (password authentication over TCP, scram-sha-256), the data live
# in the /var/lib/postgresql/data volume, the server runs as the `postgres` user, listens on every interface, stops
# on SIGINT (a fast shutdown) and `pg_isready` is on PATH for the health check.
# Differences: PostgreSQL 15, the C.UTF-8 locale instead of en_US.utf8, and no .sql.gz/.sql.xz init scripts.
ARG BASE=posemetry-standin/debian:bookworm
FROM ${BASE}
LABEL org.posemetry.standin="postgres from Debian bookworm's postgresql-15"
RUN apt-get update \
    && apt-get install -y --no-install-recommends postgresql-common \
    && sed -ri 's/#(create_main_cluster) .*$/\1 = false/' /etc/postgresql-common/createcluster.conf \
    && apt-get install -y --no-install-recommends postgresql-15 \
    && rm -rf /var/lib/apt/lists/* \
    && mkdir -p /var/run/postgresql /var/lib/postgresql/data /docker-entrypoint-initdb.d \
    && chown -R postgres:postgres /var/run/postgresql /var/lib/postgresql \
    && chmod 3777 /var/run/postgresql
ENV PG_MAJOR=15 \
    PATH=/usr/lib/postgresql/15/bin:$PATH \
    PGDATA=/var/lib/postgresql/data
COPY postgres-entrypoint.sh /usr/local/bin/docker-entrypoint.sh
VOLUME /var/lib/postgresql/data
STOPSIGNAL SIGINT
EXPOSE 5432
ENTRYPOINT ["docker-entrypoint.sh"]
CMD ["postgres"]
