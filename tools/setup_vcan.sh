#!/usr/bin/env bash
# Set up a virtual SocketCAN interface for dobhil on a Linux box (idempotent).
#
# usage: sudo tools/setup_vcan.sh [IFACE]      (default IFACE: vcan0)
#
# Then, in two terminals (see docs/hardware.md):
#   dobhil emulate configs/demo.yaml --bus socketcan:vcan0
#   dobhil run     configs/demo.yaml --bus socketcan:vcan0
#
# A real CAN interface (e.g. an ODrive on can0) is set up by hand, not by this script:
#   sudo ip link set can0 down
#   sudo ip link set can0 type can bitrate 1000000 restart-ms 100
#   sudo ip link set can0 txqueuelen 1000 up
# (restart-ms: automatic recovery from bus-off; txqueuelen: the default of 10 makes
#  send() fail with ENOBUFS under bursts.)
set -euo pipefail

usage() {
    sed -n '2,15p' "$0" | sed 's/^# \{0,1\}//'
}

case "${1:-}" in
    -h|--help) usage; exit 0 ;;
esac

IFACE="${1:-vcan0}"
if [[ $# -gt 1 ]]; then
    usage >&2
    exit 2
fi
if [[ "$(uname -s)" != "Linux" ]]; then
    echo "setup_vcan.sh: SocketCAN needs Linux (this is $(uname -s))" >&2
    exit 1
fi
SUDO=""
if [[ "$(id -u)" -ne 0 ]]; then
    SUDO="sudo"
fi

if ! lsmod 2>/dev/null | grep -q '^vcan '; then
    $SUDO modprobe vcan
fi
if ! ip link show dev "$IFACE" >/dev/null 2>&1; then
    $SUDO ip link add dev "$IFACE" type vcan
fi
$SUDO ip link set "$IFACE" txqueuelen 1000
$SUDO ip link set up "$IFACE"
ip -details link show dev "$IFACE"
echo "$IFACE is up: use --bus socketcan:$IFACE"
