#!/usr/bin/env bash
# Installs Tessera on a Debian machine (run as root, or with sudo), from this checkout:
#   1. Debian packages: Python and its venv module, a C compiler and headers (python-sane is built
#      from source), SANE for real scanners and its `test` backend, Chromium for the browser tests,
#      iproute2 and util-linux for the multi-host test in network namespaces and CPU pinning,
#      libmagic1 for IIIF's image validator (a test dependency);
#   2. a virtual environment, /opt/tessera/venv (or $TESSERA_VENV), made with the first `python3`
#      on PATH (3.11 or newer: Debian's own or another), holding Tessera installed editable from
#      this checkout with its extras (test, sane, web);
#   3. the link /usr/local/bin/tessera -> <venv>/bin/tessera.
# The tests run with that environment's Python: /opt/tessera/venv/bin/python -m pytest
# (Debian's python3 refuses pip installs into itself, PEP 668: hence the environment).
#
# Run again, it updates in place: only missing Debian packages are installed, the environment is
# kept and Tessera re-installed into it from the checkout (new dependencies, new commands).
# Without root it checks what it would have to change, says so and stops before changing anything.
#
# Usage: bash deploy/install.sh [--runtime] [--recreate]
#   --runtime   what a service host or container needs: no Chromium or test tools, extras sane,web
#   --recreate  delete the environment and make it again with the first python3 on PATH
set -euo pipefail
umask 022   # the environment is read by the service user (systemd units run as `tessera`)

here="$(cd "$(dirname "$0")/.." && pwd)"
venv="${TESSERA_VENV:-/opt/tessera/venv}"
bindir=/usr/local/bin
min_python=3.11

say() { echo "[install] $*"; }
die() { echo "[install] error: $*" >&2; exit 1; }

runtime=0
recreate=0
for arg in "$@"; do
  case "$arg" in
    --runtime) runtime=1 ;;
    --recreate) recreate=1 ;;
    -h|--help) sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//'; exit 0 ;;
    *) echo "[install] error: unknown argument '$arg' (expected --runtime, --recreate or --help)" >&2; exit 2 ;;
  esac
done
case "$venv" in /*) ;; *) die "TESSERA_VENV must be an absolute path, got '$venv'" ;; esac
[ -f "$here/pyproject.toml" ] || die "no pyproject.toml in $here: run deploy/install.sh from a Tessera checkout"
command -v dpkg-query >/dev/null && command -v apt-get >/dev/null \
  || die "dpkg-query and apt-get not found: this installer is for Debian (12 or newer) and its derivatives"

# --- what has to change (nothing is changed in this part) ---------------------------------------
debs=(python3 python3-venv python3-dev gcc libc6-dev libsane1 libsane-dev)
# libmagic1: python-magic, which IIIF's image validator (a test extra) imports
[ "$runtime" = 1 ] || debs+=(sane-utils chromium iproute2 util-linux libmagic1)
extras=test,sane,web
[ "$runtime" = 1 ] && extras=sane,web
missing=()
for p in "${debs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done

version_of() { "$1" -c 'import sys; print("%d.%d.%d" % sys.version_info[:3])' 2>/dev/null; }
new_enough() { [ "$(printf '%s\n%s\n' "$min_python" "$1" | sort -V | head -n1)" = "$min_python" ]; }

python="$(command -v python3 || true)"
if [ -n "$python" ]; then
  pyver="$(version_of "$python")" || die "$python (the first python3 on PATH) does not run"
  new_enough "$pyver" || die "$python (the first python3 on PATH) is Python $pyver; Tessera needs \
$min_python or newer: put a newer python3 first on PATH (Debian 12's /usr/bin/python3 is 3.11)"
fi

sane_disabled=0
if [ -f /etc/sane.d/dll.conf ] && grep -q '^#test$' /etc/sane.d/dll.conf; then sane_disabled=1; fi

# the first existing directory on the way to $1 (where a new directory would be created)
existing_parent() { local d="$1"; while [ ! -e "$d" ]; do d="$(dirname "$d")"; done; echo "$d"; }

if [ "$(id -u)" != 0 ]; then
  needs=()
  [ ${#missing[@]} -eq 0 ] || needs+=("install the Debian packages: ${missing[*]}")
  [ "$sane_disabled" = 0 ] || needs+=("enable SANE's test backend in /etc/sane.d/dll.conf")
  [ -w "$(existing_parent "$venv")" ] || needs+=("create or update the virtual environment $venv")
  [ -w "$bindir" ] || needs+=("link $bindir/tessera to $venv/bin/tessera")
  if [ ${#needs[@]} -gt 0 ]; then
    {
      echo "[install] needs root (it is running as $(id -un)): nothing was changed. It has to:"
      for n in "${needs[@]}"; do echo "  - $n"; done
      echo "Run it as root: sudo bash $here/deploy/install.sh${*:+ $*}"
    } >&2
    exit 1
  fi
fi

# --- changes -------------------------------------------------------------------------------------
mkdir -p "$(dirname "$venv")"
exec 9>"$venv.lock"
flock -w 900 9 || die "another deploy/install.sh holds $venv.lock for more than 15 min"

if [ ${#missing[@]} -gt 0 ]; then
  say "Debian packages: ${missing[*]}"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

# SANE ships its `test` backend disabled; the scanner tests drive it for real.
if [ "$sane_disabled" = 1 ]; then
  sed -i 's/^#test$/test/' /etc/sane.d/dll.conf
fi

hash -r
python="$(command -v python3)" || die "python3 is still not on PATH after installing Debian's python3"
pyver="$(version_of "$python")" || die "$python does not run"
new_enough "$pyver" || die "$python is Python $pyver; Tessera needs $min_python or newer"
# the interpreter itself, not a launcher (a pyenv shim picks its Python from the current directory),
# and the base one if it belongs to a virtual environment (e.g. this one, activated, with --recreate)
python="$("$python" -c 'import os, sys; print(sys.executable if sys.prefix == sys.base_prefix else
  os.path.join(sys.base_prefix, "bin", "python%d.%d" % sys.version_info[:2]))')"
[ -x "$python" ] || die "cannot find the interpreter behind the first python3 on PATH (tried $python)"

if [ "$recreate" = 1 ] && [ -e "$venv" ]; then
  say "removing $venv (--recreate)"
  rm -rf "$venv"
fi
if [ -e "$venv" ]; then
  if envver="$(version_of "$venv/bin/python")" && new_enough "$envver"; then
    say "updating $venv (Python $envver; --recreate makes it again with $python, $pyver)"
  else
    say "$venv is not a working Python $min_python+ environment (its interpreter moved or was removed): making it again"
    rm -rf "$venv"
  fi
fi
fresh=0
if [ ! -e "$venv" ]; then
  say "creating $venv with $python (Python $pyver)"
  fresh=1
  # a failed first install leaves no half-made environment behind
  trap 'if [ "$fresh" = 1 ]; then rm -rf "$venv"; echo "[install] failed: removed the unfinished $venv" >&2; fi' EXIT
  "$python" -m venv "$venv"
fi

say "Tessera from $here with extras [$extras] into $venv (pip: a few minutes the first time)"
"$venv/bin/python" -m pip install -q --disable-pip-version-check -e "$here[$extras]"
"$venv/bin/tessera" --help >/dev/null || die "$venv/bin/tessera does not start"
fresh=0

ln -sfn "$venv/bin/tessera" "$bindir/tessera"
say "linked $bindir/tessera -> $venv/bin/tessera"

# systemd units run as the `tessera` user: the editable install reads the checkout itself.
if command -v runuser >/dev/null && id nobody >/dev/null 2>&1 && [ "$(id -u)" = 0 ] \
   && ! runuser -u nobody -- test -r "$here/services/cli/__init__.py" 2>/dev/null; then
  say "note: other users cannot read $here; the systemd units (User=tessera) need to: put the checkout" \
      "where they can (e.g. /opt/tessera/src) and run this installer from there"
fi
tests=""
[ "$runtime" = 1 ] || tests="; tests: $venv/bin/python -m pytest"
say "done: 'tessera' runs $venv (Python $(version_of "$venv/bin/python"))$tests"
