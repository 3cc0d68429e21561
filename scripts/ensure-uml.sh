#!/usr/bin/env bash
# Make sure the vcan tests can run: natively when the kernel has vcan, otherwise inside
# user-mode Linux (Debian's user-mode-linux + kmod), which `make test` installs when it is root.
# The boot itself is scripts/uml_run.py, driven by tests/conftest.py for tests marked `vcan`.
set -u
if ip link add dev hilbo-probe0 type vcan 2>/dev/null; then
  ip link del hilbo-probe0 2>/dev/null
  # the kernel has vcan (and we may create links): make sure vcan0 is there and up
  ip link show vcan0 >/dev/null 2>&1 || ip link add dev vcan0 type vcan
  ip link set up vcan0
  exit 0
fi
if command -v linux.uml >/dev/null 2>&1 && command -v insmod >/dev/null 2>&1 \
   && command -v ip >/dev/null 2>&1 \
   && ls /usr/lib/uml/modules/*/kernel/drivers/net/can/vcan.ko >/dev/null 2>&1; then
  exit 0
fi
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  echo "installing user-mode-linux and kmod for the vcan tests" >&2
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq user-mode-linux kmod iproute2) >/dev/null 2>&1 \
    || echo "warning: could not install user-mode-linux; vcan tests will skip" >&2
else
  echo "warning: no vcan and no user-mode-linux (not root); vcan tests will skip" >&2
fi
exit 0
