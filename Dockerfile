# One image for every role; the command picks the service (docker-compose.yml).
# BASE: a registry's python:3.11-slim for users; here a Debian bookworm root
# filesystem imported locally (docker/setup-podman.sh), since no registry is reachable.
ARG BASE=python:3.11-slim
FROM ${BASE}
# dependencies come from a wheelhouse built on the host (docker/setup-podman.sh):
# no package index is used inside the build
# MuJoCo and Pinocchio's wheels need the GNU OpenMP runtime; the local base has it,
# a python:3.11-slim base gets it from Debian
RUN ldconfig -p | grep -q libgomp.so.1 || (apt-get update && apt-get install -y --no-install-recommends libgomp1 \
    && rm -rf /var/lib/apt/lists/*)
# The dependencies first, in a layer of their own: it changes only when they do,
# so a rebuild after a change to the project reuses it.  pip byte-compiles one file at
# a time, most of the layer's time; compileall does it on every core and leaves out what
# no service imports (as the Makefile does for .venv): the layer in 17 s instead of 59
COPY docker/wheelhouse /wheelhouse
RUN python3 -m venv /opt/etar \
 && /opt/etar/bin/pip install --no-index --no-compile /wheelhouse/*.whl \
 && rm -rf /wheelhouse \
 && (/opt/etar/bin/python -m compileall -q -j 0 -x '/(OpenGL|pip|setuptools|tests?)/' /opt/etar/lib >/dev/null || true)
COPY docker/project-wheel /project-wheel
RUN /opt/etar/bin/pip install --no-index --no-deps /project-wheel/*.whl && rm -rf /project-wheel
COPY scenarios /app/scenarios
ENV PATH=/opt/etar/bin:$PATH PYTHONUNBUFFERED=1 NUMBA_CACHE_DIR=/opt/etar/numba-cache
WORKDIR /app
# numba's kernels compiled into the image once: otherwise every container compiles its own
# on start (the cell's before the robot is ready, EM's in the runner's learning); taken
# from the build cache when nothing they are compiled from changed (docker/image-kernels.sh)
COPY docker/image-kernels.sh /usr/local/bin/
RUN --mount=type=cache,id=etar-numba-kernels,target=/var/cache/etar-kernels \
    sh /usr/local/bin/image-kernels.sh /var/cache/etar-kernels
CMD ["etar-bench", "--help"]
