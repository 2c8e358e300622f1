# syntax=docker/dockerfile:1.7
#
# The Rerun viewer (web viewer and gRPC proxy) of the version the service links: the rerun-sdk
# wheel carries the full `rerun` binary.

FROM python:3.11-slim-bookworm
ARG RERUN_VERSION=0.36.3
RUN pip install --no-cache-dir "rerun-sdk==${RERUN_VERSION}" \
    && groupadd --system --gid 10002 rerun \
    && useradd --system --uid 10002 --gid rerun --create-home rerun
USER 10002:10002
RUN rerun analytics disable
EXPOSE 9876 9090
ENTRYPOINT ["rerun"]
