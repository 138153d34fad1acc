#!/usr/bin/env bash
# Installs everything Tessera needs on a fresh Debian machine (run as root, or with sudo):
# Debian packages (SANE for real scanners and its `test` backend, Chromium for the browser tests,
# iproute2 and util-linux for the multi-host test in network namespaces and CPU pinning),
# then the Python package with its test extras into the current Python.
# Safe to run again: it only installs what is missing.
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"

debs=(libsane1 libsane-dev sane-utils chromium iproute2 util-linux)
missing=()
for p in "${debs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "[install] Debian packages: ${missing[*]}"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

# SANE ships its `test` backend disabled; the scanner tests drive it for real.
if [ -f /etc/sane.d/dll.conf ] && grep -q '^#test' /etc/sane.d/dll.conf; then
  sed -i 's/^#test$/test/' /etc/sane.d/dll.conf
fi

echo "[install] Python packages"
python3 -m pip install -q --disable-pip-version-check -e "$here[test,sane,web]"
echo "[install] done: the 'tessera' command is ready"
