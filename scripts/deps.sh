#!/usr/bin/env bash
# Installs the Debian 12 packages the project needs, only those that are missing (so a second
# run is quick). Sourced by scripts/run.sh and scripts/test.sh; needs root (or sudo) to install.
# ensure_packages PKG... installs further packages the same way (run.sh: the plotting ones).
set -euo pipefail
ensure_packages() {
  local missing=()
  for p in "$@"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
  done
  if ((${#missing[@]})); then
    echo "Installing missing packages: ${missing[*]}"
    local sudo_cmd=""
    [ "$(id -u)" -eq 0 ] || sudo_cmd="sudo"
    $sudo_cmd apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq --no-install-recommends "${missing[@]}"
  fi
}
ensure_packages g++ cmake ninja-build pkg-config \
  libeigen3-dev libcgal-dev libembree-dev libassimp-dev libtbb-dev \
  nlohmann-json3-dev libcli11-dev libhdf5-dev libgtest-dev libbenchmark-dev
