# Stand-in for the official `redis:7`, from Debian bookworm's redis-server 7.0 (build.sh beside this file builds it
# only where that image can be neither found locally nor pulled).
#
# The official image's contract that docker-compose.yml relies on: `redis-server ...` as the command, run as the
# unprivileged `redis` user, in the /data volume (its working directory, so append-only files land there),
# listening on every interface without protected mode (the container network is the boundary; the official build
# turns protected mode off, a Debian build keeps it on), and `redis-cli` for the health check.
ARG BASE=posemetry-standin/debian:bookworm
FROM ${BASE}
LABEL org.posemetry.standin="redis:7 from Debian bookworm's redis-server"
RUN apt-get update \
    && apt-get install -y --no-install-recommends redis-server \
    && rm -rf /var/lib/apt/lists/* \
    && mkdir -p /data \
    && chown redis:redis /data
COPY redis-entrypoint.sh /usr/local/bin/docker-entrypoint.sh
VOLUME /data
WORKDIR /data
EXPOSE 6379
ENTRYPOINT ["docker-entrypoint.sh"]
CMD ["redis-server"]
