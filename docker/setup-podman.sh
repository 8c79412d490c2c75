#!/usr/bin/env bash
# Make this machine able to run docker-compose.yml on podman (no Docker engine here):
# packages, podman's configuration, its Docker-compatible socket, a local Debian base
# image (no registry is reachable), and a wheelhouse of the project and its
# dependencies (images install from it with --no-index).  Idempotent; prints what it does.
#   usage: docker/setup-podman.sh [VENV_PYTHON]
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
root="$(dirname "$here")"
py="${1:-$root/.venv/bin/python}"
sock="${ETAR_PODMAN_SOCKET:-/tmp/etar-podman.sock}"
state="$root/.podman"
mkdir -p "$state"

need=()
for cmd in podman docker-compose debootstrap runc; do command -v "$cmd" >/dev/null || need+=("$cmd"); done
if ((${#need[@]})); then
  echo "setup-podman: installing ${need[*]}"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq podman runc docker-compose debootstrap >/dev/null
fi
install -D -m 644 "$here/containers.conf" /etc/containers/containers.conf

if ! curl -s --unix-socket "$sock" http://d/_ping 2>/dev/null | grep -q OK; then
  echo "setup-podman: starting podman's Docker-compatible service on $sock"
  # from /: the service outlives this checkout, and a conmon it spawns in a deleted
  # working directory fails every container ("write child: broken pipe")
  (cd / && exec nohup podman system service --time=0 "unix://$sock") >"$state/service.log" 2>&1 </dev/null &
  for _ in $(seq 50); do curl -s --unix-socket "$sock" http://d/_ping 2>/dev/null | grep -q OK && break; sleep 0.2; done
fi

if ! podman image exists localhost/etar-base:bookworm-2; then
  echo "setup-podman: building the Debian base image (debootstrap, about a minute)"
  rm -rf "$state/rootfs"
  debootstrap --variant=minbase --include=python3,python3-venv,ca-certificates,libgomp1 bookworm "$state/rootfs" \
    >"$state/debootstrap.log" 2>&1
  tar -C "$state/rootfs" -c . | podman import - localhost/etar-base:bookworm-2 >/dev/null
  rm -rf "$state/rootfs"
fi

stamp="$state/wheelhouse.stamp"
if [[ ! -f "$stamp" || "$root/pyproject.toml" -nt "$stamp" || "$root/setup.py" -nt "$stamp" \
      || -n "$(find "$root/etar" "$root/kernel_plumbing" "$root/robot_sim" "$root/services" \( -name '*.py' -o -name '*.cpp' \) -newer "$stamp" -print -quit)" ]]; then
  echo "setup-podman: building the wheelhouse"
  rm -rf "$root/docker/wheelhouse" "$root/docker/project-wheel"
  "$py" -m pip wheel -q --wheel-dir "$root/docker/wheelhouse" "$root" 2>"$state/wheel.log" >/dev/null
  # the project's own wheel apart: the image installs the dependencies in a layer it can reuse
  mkdir -p "$root/docker/project-wheel"
  mv "$root"/docker/wheelhouse/etar_testbench-*.whl "$root/docker/project-wheel/"
  touch "$stamp"
fi
echo "setup-podman: ready (DOCKER_HOST=unix://$sock)"
