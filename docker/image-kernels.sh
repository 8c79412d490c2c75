#!/bin/sh
# numba's kernels for the image (the Dockerfile's last step), compiled only when what they
# are compiled from changed: the kernels' packages (etar, robot_sim, kernel_plumbing, and
# services: its message writer's and its sensor's kernels, which a container compiled at the
# service's start, 4-8 s, when the image left them out), which of them are compiled
# (services/run/kernel_cache.py), the installed libraries, numba and this CPU.  A build that
# changed none of these takes the kernels a previous build compiled, from a build cache
# (CACHE, a RUN --mount=type=cache) keyed by all of that; otherwise
# `python -m services.run.kernel_cache` compiles them (~50 s of CPU) and the cache keeps
# them for the next builds.
#
# numba takes a kernel from its cache only if the source file's mtime and size are the ones
# it was compiled from: the installed files of the four packages get one fixed mtime here
# (the zip epoch; pip gives them the time of the install), and their bytecode is compiled
# again against it.
#   usage: image-kernels.sh CACHE     (NUMBA_CACHE_DIR: where the image keeps its kernels)
set -eu
cache="$1"
: "${NUMBA_CACHE_DIR:?image-kernels.sh: NUMBA_CACHE_DIR must say where the image keeps its kernels}"
# (not by importing them: the cell's kernels compile at import)
site="$(python -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
packages="$site/etar $site/robot_sim $site/kernel_plumbing $site/services"
# shellcheck disable=SC2086  # the package folders are separate words
find $packages -name '*.py' -exec touch -d @315532800 {} +
# shellcheck disable=SC2086
python -m compileall -q $packages >/dev/null
key="$( {
  # the kernels' sources, and which kernels are compiled: what services.run.kernel_cache runs
  # shellcheck disable=SC2086
  find $packages -name '*.py' | sort | while read -r f; do
    echo "$f"; cat "$f"
  done
  python -m pip freeze --all
  python -c 'import numba, llvmlite.binding as ll; print(numba.__version__, ll.get_host_cpu_name(), ll.get_host_cpu_features().flatten())'
} | sha256sum | cut -c1-32)"
if [ -d "$cache/$key" ]; then
  echo "image-kernels: numba's kernels from the build cache ($key): their sources, the libraries and the CPU are unchanged"
  cp -a "$cache/$key" "$NUMBA_CACHE_DIR"
  touch "$cache/$key"  # the newest used, for the pruning below
else
  echo "image-kernels: compiling numba's kernels ($key)"
  python -m services.run.kernel_cache
  # whole or not at all: a build stopped half-way must not leave half the kernels under the key
  rm -rf "$cache/$key.partial"
  cp -a "$NUMBA_CACHE_DIR" "$cache/$key.partial"
  mv "$cache/$key.partial" "$cache/$key"
  # the four newest (~5 MB each), so that going back to a branch finds its kernels: a cache
  # of every past build would grow without end
  ls -1t "$cache" | tail -n +5 | while read -r old; do rm -rf "${cache:?}/$old"; done
fi
