#!/bin/sh
# Create and bring up a SocketCAN interface for hilbo on a Linux machine.
#
#   scripts/vcan-setup.sh                 # vcan0 (virtual bus shared by local processes)
#   scripts/vcan-setup.sh vcan1           # another virtual bus
#   scripts/vcan-setup.sh can0 1000000    # a real adapter at 1 Mbit/s (the exosuit bus)
#   scripts/vcan-setup.sh --print [IF]    # only print the commands
#
# Runs the commands with sudo when not root. Same commands as drivers.exosuit.vcan_setup
# (`hilbo vcan-setup`). To keep vcan0 across reboots, see docs/exosuit-bus.md.
set -eu

print_only=0
if [ "${1:-}" = "--print" ]; then print_only=1; shift; fi
ifname=${1:-vcan0}
bitrate=${2:-1000000}

case "$ifname" in
  *[!A-Za-z0-9_.-]*|"") echo "vcan-setup: bad interface name '$ifname'" >&2; exit 2 ;;
esac
if [ "${#ifname}" -gt 15 ]; then echo "vcan-setup: interface name '$ifname' longer than 15" >&2; exit 2; fi
case "$bitrate" in
  *[!0-9]*|"") echo "vcan-setup: bad bitrate '$bitrate'" >&2; exit 2 ;;
esac

case "$ifname" in
  vcan*)
    commands="modprobe vcan
ip link show $ifname >/dev/null 2>&1 || ip link add dev $ifname type vcan
ip link set up $ifname" ;;
  *)
    commands="ip link set $ifname down
ip link set $ifname type can bitrate $bitrate restart-ms 100
ip link set up $ifname" ;;
esac

if [ "$print_only" = 1 ]; then
  printf '%s\n' "$commands"
  exit 0
fi
if [ "$(id -u)" = 0 ]; then
  printf '%s\n' "$commands" | sh -e
else
  printf '%s\n' "$commands" | sudo sh -e
fi
ip -details link show "$ifname"
