#!/bin/bash
# `hilbo run` on the virtual devices, as README "A dry run on the virtual devices" (python-can-remote
# route: this machine's kernel has no vcan), with the example config unchanged except its ports,
# output directory and `auto_resume_s = 10` (nobody presses "r"); with SESSION_MIN given, also
# `session_min = SESSION_MIN` and `budget_min = SESSION_MIN` (so the session's limit, not the
# optimisation budget, ends it). Prints hilbo run's last line and the summary's walking time.
#
#   docs/results/supervision/run_virtual.sh SPEED OUTDIR [SESSION_MIN]   # SPEED 1 = real time (about 63 min)
set -euo pipefail
SPEED=${1:?speed factor, 1 = real time}
OUT=$(realpath -m "${2:?output directory}")
SESSION_MIN=${3:-}
V=$(cd "$(dirname "$0")/../../.." && pwd)/.venv/bin
mkdir -p "$OUT"
cd "$OUT"
"$V/hilbo" config example \
  | sed -e "s|^out_dir = \"sessions\" |out_dir = \"$OUT/sessions\"|" \
        -e 's|^interface = "socketcan"  |interface = "remote"     |' \
        -e 's|^channel = "vcan0"  |channel = "ws://127.0.0.1:54771/"|' \
        -e 's|^# auto_resume_s = 10.0|auto_resume_s = 10.0|' -e 's|^port = 5050|port = 5071|' \
        -e "${SESSION_MIN:+s|^# session_min = 60.0 |session_min = $SESSION_MIN |}" \
        -e "${SESSION_MIN:+s|^budget_min = 40.0 |budget_min = $SESSION_MIN |}" > session.toml
EPOCH=$(date +%s)
"$V/python" -m can_remote --interface virtual --channel run --host 127.0.0.1 --port 54771 > can.log 2>&1 &
PIDS=$!
trap 'kill $PIDS 2>/dev/null || true' EXIT
sleep 2
"$V/hilbo" virtual-exosuit --interface remote --channel ws://127.0.0.1:54771/ --speed "$SPEED" \
  --epoch "$EPOCH" --feedback-hz 100 > exosuit.log 2>&1 &
PIDS="$PIDS $!"
"$V/hilbo" virtual-cart --port 5071 --speed "$SPEED" --epoch "$EPOCH" --seed 1 \
  --can-interface remote --can-channel ws://127.0.0.1:54771/ > cart.log 2>&1 &
PIDS="$PIDS $!"
sleep 2
"$V/hilbo" run session.toml --no-view > run.out 2> run.err < /dev/null
tail -n 1 run.err
"$V/python" -c "import json, sys; print(json.dumps(json.load(open(sys.argv[1]))['walking']))" "$(tail -n 1 run.out)"
