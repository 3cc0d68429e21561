#!/usr/bin/env bash
# Make sure the vcan tests can run: natively when the kernel has vcan, otherwise inside
# user-mode Linux (Debian's user-mode-linux + kmod), which `make test` installs when it is root.
# On a CPU with AMX, UML needs a small preloaded shim that scripts/uml_run.py compiles with cc.
# HILBO_GUEST=qemu selects a (much slower) QEMU guest instead: the Debian kernel + static busybox.
# The boot itself is scripts/uml_run.py, driven by tests/conftest.py for tests marked `vcan`.
set -u
if ip link add dev hilbo-probe0 type vcan 2>/dev/null; then
  ip link del hilbo-probe0 2>/dev/null
  # the kernel has vcan (and we may create links): make sure vcan0 is there and up
  ip link show vcan0 >/dev/null 2>&1 || ip link add dev vcan0 type vcan
  ip link set up vcan0
  exit 0
fi
apt_install() {
  if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
    echo "installing $* for the vcan tests" >&2
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@") >/dev/null 2>&1 \
      || echo "warning: could not install $*; vcan tests will skip" >&2
  else
    echo "warning: no vcan, and cannot install $* (not root); vcan tests will skip" >&2
  fi
}
if [ "${HILBO_GUEST:-uml}" = "qemu" ]; then
  if command -v qemu-system-x86_64 >/dev/null 2>&1 && command -v busybox >/dev/null 2>&1 \
     && command -v modprobe >/dev/null 2>&1 && command -v ip >/dev/null 2>&1 \
     && ls /lib/modules/*/kernel/drivers/net/can/vcan.ko* >/dev/null 2>&1; then
    exit 0
  fi
  apt_install qemu-system-x86 busybox-static linux-image-amd64 kmod iproute2
  exit 0
fi
need="user-mode-linux kmod iproute2"
if command -v linux.uml >/dev/null 2>&1 && command -v insmod >/dev/null 2>&1 \
   && command -v ip >/dev/null 2>&1 \
   && ls /usr/lib/uml/modules/*/kernel/drivers/net/can/vcan.ko >/dev/null 2>&1; then
  need=""
fi
# the AMX shim (scripts/uml_xstate_shim.c) is compiled with cc
if grep -qw amx_tile /proc/cpuinfo 2>/dev/null && ! command -v cc >/dev/null 2>&1; then
  need="$need gcc libc6-dev"
fi
# shellcheck disable=SC2086  # word splitting of the package list is intended
[ -z "$need" ] || apt_install $need
exit 0
