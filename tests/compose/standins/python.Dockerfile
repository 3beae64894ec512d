# Stand-in for the official `python:3.11-slim`, from Debian bookworm's own Python 3.11 (build.sh beside this file
# builds it only where that image can be neither found locally nor pulled).
#
# What the project's Dockerfile relies on, provided as the official image does: `python` and `pip` in
# /usr/local/bin, on the default PATH; `pip install` into the image's Python without complaint (Debian marks its
# system Python as externally managed, so the interpreter here is a virtual environment rooted at /usr/local:
# packages land in /usr/local/lib/python3.11/site-packages and scripts in /usr/local/bin, as in the official
# image); `python -m venv`; a recent pip; CA certificates; `useradd`; LANG=C.UTF-8.
# Differences: Debian's 3.11 patch release rather than the newest one, and Debian's build options. And one addition
# for the machine that builds it: the certificate authorities it trusts beyond Debian's (its
# /usr/local/share/ca-certificates, passed by build.sh as the `host-ca` build context, e.g. a TLS-inspecting egress
# proxy's), with pip pointed at the system bundle, so that `pip install` in builds on this image reaches PyPI as
# pip on the host does. Nothing of that is in the repository.
ARG BASE=posemetry-standin/debian:bookworm
FROM ${BASE}
LABEL org.posemetry.standin="python:3.11-slim from Debian bookworm's python3.11"
ENV LANG=C.UTF-8
RUN apt-get update \
    && apt-get install -y --no-install-recommends python3 python3-venv ca-certificates netbase tzdata \
    && rm -rf /var/lib/apt/lists/*
COPY --from=host-ca / /usr/local/share/ca-certificates/
RUN update-ca-certificates \
    && printf '[global]\ncert = /etc/ssl/certs/ca-certificates.crt\n' >/etc/pip.conf \
    && python3 -m venv /usr/local \
    && /usr/local/bin/pip install --no-cache-dir --disable-pip-version-check --upgrade pip \
    && python --version && pip --version
CMD ["python3"]
