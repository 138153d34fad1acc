#!/usr/bin/env bash
# A lab on one machine: four network namespaces joined by veth pairs (iproute2), as separate hosts.
#
#   broker  10.<net>.0.1   the broker (journal on its own "local disk")
#   w1      10.<net>.0.2   worker host 1
#   w2      10.<net>.0.3   worker host 2
#   scanner 10.<net>.0.4   the bench PC (spool + outbox on its own "local disk")
#
# The hosts reach each other only through a bridge in a fifth namespace (the "switch"), never through
# the machine's own interfaces or loopback. The storage root is one directory bind-mounted at
# STATE/mnt/tessera, the same path on every host as an NFS share would be; the generated config turns
# HDF5 file locking off and refuses to create the root (a missing mount is "storage unreachable").
#
# Usage (root; every command takes the same --prefix/--state/--net):
#   deploy/multihost.sh up      [--prefix tsl] [--state DIR] [--net 77] [--curve]
#                               create hosts, share, STATE/lab.toml; --curve: CURVE keys for every host
#                               (`tessera keys`, STATE/keys) and per-host configs STATE/hosts/<host>/lab.toml
#   deploy/multihost.sh exec    HOST COMMAND...     run a command on a host (ip netns exec)
#   deploy/multihost.sh tessera HOST ARGS...        run `tessera ARGS --config STATE/lab.toml` on a host
#   deploy/multihost.sh cut     HOST                cut the host's cable (link down at the switch)
#   deploy/multihost.sh heal    HOST                plug it back in
#   deploy/multihost.sh status                      hosts, addresses, links
#   deploy/multihost.sh down                        kill what runs in the hosts, remove them, unmount
#
# Example:
#   sudo deploy/multihost.sh up --state /tmp/lab
#   sudo deploy/multihost.sh tessera broker broker &
#   sudo deploy/multihost.sh tessera w1 worker solver &
#   sudo deploy/multihost.sh tessera w2 worker features &
#   sudo deploy/multihost.sh tessera scanner scanner --count 2
#   sudo deploy/multihost.sh down --state /tmp/lab
set -euo pipefail

PREFIX=tsl
CURVE=0
STATE=/tmp/tessera-multihost
NET=77
HOSTS=(broker w1 w2 scanner)
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"

die() { echo "multihost: $*" >&2; exit 1; }

cmd="${1:-}"; [ -n "$cmd" ] || die "usage: $0 up|exec|tessera|cut|heal|status|down [options]"; shift
args=()
while [ $# -gt 0 ]; do
  case "$1" in
    --prefix) PREFIX="$2"; shift 2 ;;
    --state) STATE="$2"; shift 2 ;;
    --net) NET="$2"; shift 2 ;;
    --curve) CURVE=1; shift ;;
    *) args+=("$1"); shift ;;
  esac
done
[[ "$PREFIX" =~ ^[a-z][a-z0-9]{0,5}$ ]] || die "--prefix must be 1-6 lower-case letters/digits (interface names are short)"
[[ "$NET" =~ ^[0-9]+$ ]] && [ "$NET" -ge 1 ] && [ "$NET" -le 254 ] || die "--net must be 1..254 (addresses 10.NET.0.x)"
SWITCH="$PREFIX-switch"
SHARE="$STATE/share"           # the file server's export
MOUNT="$STATE/mnt/tessera"     # where every host "mounts" it
CONFIG="$STATE/lab.toml"

ns() { echo "$PREFIX-$1"; }
tessera_here() { PYTHONPATH="$REPO${PYTHONPATH:+:$PYTHONPATH}" "${PYTHON:-python3}" -c \
  "import sys; from services.cli import main; sys.exit(main())" "$@"; }
addr() { local i; for i in "${!HOSTS[@]}"; do [ "${HOSTS[$i]}" = "$1" ] && { echo "10.$NET.0.$((i + 1))"; return; }; done
         die "unknown host '$1' (hosts: ${HOSTS[*]})"; }
need_root() { [ "$(id -u)" = 0 ] || die "needs root (network namespaces)"; ip netns list >/dev/null 2>&1 || die "ip netns unavailable"; }

up() {
  need_root
  [ -e "/run/netns/$SWITCH" ] && die "already up (prefix $PREFIX); run: $0 down --prefix $PREFIX --state $STATE"
  mkdir -p "$SHARE" "$MOUNT"
  mountpoint -q "$MOUNT" || mount --bind "$SHARE" "$MOUNT"
  ip netns add "$SWITCH"
  ip -n "$SWITCH" link add br0 type bridge
  ip -n "$SWITCH" link set br0 up
  ip -n "$SWITCH" link set lo up
  for h in "${HOSTS[@]}"; do
    local n; n="$(ns "$h")"
    ip netns add "$n"
    ip -n "$n" link set lo up
    # the host end is created inside the host, the switch end is moved to the switch
    ip -n "$n" link add eth0 type veth peer name "$PREFIX-$h" netns "$SWITCH"
    ip -n "$n" addr add "$(addr "$h")/24" dev eth0
    ip -n "$n" link set eth0 up
    ip -n "$SWITCH" link set "$PREFIX-$h" master br0
    ip -n "$SWITCH" link set "$PREFIX-$h" up
    mkdir -p "$STATE/hosts/$h"
  done
  cat > "$CONFIG" <<EOF
# written by deploy/multihost.sh: the same file on every host (like configs/lab.toml)
[storage]
root = "$MOUNT"
file_locking = false
create_root = false

[broker]
host = "$(addr broker)"
bind = "$(addr broker)"
port = 5555
feed_port = 5556
journal_dir = "$STATE/hosts/broker/journal"
heartbeat_interval_s = 0.5
heartbeat_liveness = 6

[worker]
reconnect_min_s = 0.25
reconnect_max_s = 2.0
shutdown_grace_s = 30.0

[client]
timeout_s = 3.0
retries = 3

[scanner]
spool_dir = "$STATE/hosts/scanner/spool"
drain_interval_s = 0.5
EOF
  if [ "$CURVE" = 1 ]; then
    # one key pair per host, all admitted by the broker; each host's config names its own secret key
    local keys="$STATE/keys"
    tessera_here keys init "$keys" >/dev/null
    for h in "${HOSTS[@]}"; do
      # a host here runs several stages and tools: its key may do everything (docs/security.md, roles)
      [ "$h" = broker ] || tessera_here keys add "$h" --role admin --dir "$keys" >/dev/null
      { cat "$CONFIG"; echo; echo "[security]"; echo "curve = true"
        if [ "$h" = broker ]; then
          echo "broker_secret_key = \"$keys/broker.key_secret\""; echo "authorized_keys = \"$keys/authorized\""
          # the broker host's own tools (tessera status there) use the broker's pair
          echo "secret_key = \"$keys/broker.key_secret\""
          cp "$keys/broker.key" "$keys/authorized/broker.key"
        else
          echo "secret_key = \"$keys/hosts/$h.key_secret\""
        fi
        echo "broker_public_key = \"$keys/broker.key\""; } > "$STATE/hosts/$h/lab.toml"
    done
  fi
  echo "up: hosts ${HOSTS[*]} on 10.$NET.0.0/24 (namespaces $PREFIX-*), storage $MOUNT, config $CONFIG$([ "$CURVE" = 1 ] && echo ", CURVE keys $STATE/keys")"
}

down() {
  need_root
  for h in "${HOSTS[@]}" switch; do
    local n; n="$(ns "$h")"
    if [ -e "/run/netns/$n" ]; then
      # whatever still runs in the host goes down with it (only processes inside this namespace)
      local pids; pids="$(ip netns pids "$n" 2>/dev/null || true)"
      [ -n "$pids" ] && kill -TERM $pids 2>/dev/null || true
    fi
  done
  sleep 0.5
  for h in "${HOSTS[@]}" switch; do
    local n; n="$(ns "$h")"
    if [ -e "/run/netns/$n" ]; then
      local pids; pids="$(ip netns pids "$n" 2>/dev/null || true)"
      [ -n "$pids" ] && kill -KILL $pids 2>/dev/null || true
      ip netns del "$n"
    fi
  done
  if mountpoint -q "$MOUNT" 2>/dev/null; then umount "$MOUNT"; fi
  echo "down: prefix $PREFIX removed (state kept in $STATE)"
}

status() {
  for h in "${HOSTS[@]}"; do
    local n; n="$(ns "$h")"
    if [ -e "/run/netns/$n" ]; then
      local link; link="$(ip -n "$SWITCH" -br link show "$PREFIX-$h" 2>/dev/null | awk '{print $2}')"
      local ip4; ip4="$(ip -n "$n" -br -4 addr show eth0 2>/dev/null | awk '{print $3}')"
      printf '%-8s %-16s cable %-6s processes %s\n' "$h" "${ip4:-?}" "${link:-?}" "$(ip netns pids "$n" | wc -l)"
    else
      printf '%-8s absent\n' "$h"
    fi
  done
  mountpoint -q "$MOUNT" 2>/dev/null && echo "storage $MOUNT mounted" || echo "storage $MOUNT not mounted"
}

case "$cmd" in
  up) up ;;
  down) down ;;
  status) status ;;
  exec)
    [ ${#args[@]} -ge 2 ] || die "usage: $0 exec HOST COMMAND..."
    addr "${args[0]}" >/dev/null
    exec ip netns exec "$(ns "${args[0]}")" "${args[@]:1}" ;;
  tessera)
    [ ${#args[@]} -ge 2 ] || die "usage: $0 tessera HOST SUBCOMMAND [ARGS...]"
    addr "${args[0]}" >/dev/null
    h="${args[0]}"
    cd "$STATE/hosts/$h"
    [ -f "$STATE/hosts/$h/lab.toml" ] && CONFIG="$STATE/hosts/$h/lab.toml"   # per-host config (--curve)
    # own UTS namespace too, so the host name (what `tessera status` lists workers by) is the host's
    exec ip netns exec "$(ns "$h")" unshare --uts -- sh -c 'hostname "$0" && exec "$@"' "$PREFIX-$h" \
      env PYTHONPATH="$REPO${PYTHONPATH:+:$PYTHONPATH}" \
      "${PYTHON:-python3}" -c "import sys; from services.cli import main; sys.exit(main())" \
      "${args[@]:1}" --config "$CONFIG" ;;
  cut|heal)
    [ ${#args[@]} -eq 1 ] || die "usage: $0 $cmd HOST"
    addr "${args[0]}" >/dev/null
    ip -n "$SWITCH" link set "$PREFIX-${args[0]}" "$([ "$cmd" = cut ] && echo down || echo up)"
    echo "$cmd: ${args[0]}" ;;
  *) die "unknown command '$cmd'" ;;
esac
