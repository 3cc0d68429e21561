#!/bin/sh
# Run pytest inside user-mode Linux with SocketCAN vcan0 up, e.g.
#
#   scripts/uml-pytest.sh -m vcan -q               # only the vcan tests
#   scripts/uml-pytest.sh tests/drivers -q          # a whole directory, natively inside UML
#
# This is what tests/conftest.py does by itself for tests marked `vcan` when the kernel has no
# vcan (a plain `pytest -m vcan` is enough); this wrapper is for running anything else in the
# guest by hand. Needs user-mode-linux, kmod, iproute2 (scripts/ensure-uml.sh installs them).
# Environment: PYTHON (default .venv/bin/python), HILBO_UML_TIMEOUT_S (default 240).
set -eu
root=$(cd "$(dirname "$0")/.." && pwd)
py=${PYTHON:-$root/.venv/bin/python}
cd "$root"
basetemp=$(mktemp -d /tmp/hilbo-uml-pytest.XXXXXX)
status=0
"$py" scripts/uml_run.py --timeout "${HILBO_UML_TIMEOUT_S:-240}" -- \
  "$py" -m pytest -p no:cacheprovider --basetemp "$basetemp/t" "$@" || status=$?
rm -rf "$basetemp"
exit "$status"
