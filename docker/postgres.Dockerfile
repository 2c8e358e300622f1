# PostgreSQL 15 with pg_partman, the server of docker/compose.postgres.yaml. The official image
# carries the PostgreSQL project's Debian repository, which packages pg_partman for each major
# version.
FROM postgres:15-bookworm

# The extension follows the repository's updates for PostgreSQL 15 rather than a pinned version.
# hadolint ignore=DL3008
RUN apt-get update \
    && apt-get install --yes --no-install-recommends postgresql-15-partman \
    && rm -rf /var/lib/apt/lists/*
