# The gyro bench service image: API, bench worker and simulated bench (one image, three commands).
#   docker build -t gyrobench .
# python:3.11-slim; the package is installed from this source tree (pip install .) with the pinned
# versions of constraints.txt (the same set scripts/install.sh installs), so its data files
# (dashboard pages, migration scripts, simulator scenarios) must be declared as package data.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

WORKDIR /app
COPY pyproject.toml README.md constraints.txt ./
COPY bench ./bench
COPY procedures ./procedures
COPY api ./api
RUN pip install -c constraints.txt . \
    && bench --help >/dev/null \
    && useradd --create-home --uid 1000 bench \
    && mkdir -p /sim \
    && chown bench /sim

USER bench
WORKDIR /home/bench
EXPOSE 8000
CMD ["bench", "--help"]
