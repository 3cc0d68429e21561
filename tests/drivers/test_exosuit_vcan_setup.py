"""vcan / CAN adapter set-up commands, and the standalone script that must print the same."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from drivers.errors import DriverConfigError
from drivers.exosuit.vcan_setup import (
    can_setup_commands,
    persistent_vcan_files,
    setup_script,
    vcan_setup_commands,
)

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "vcan-setup.sh"


def test_vcan_commands() -> None:
    assert vcan_setup_commands() == [
        "modprobe vcan",
        "ip link show vcan0 >/dev/null 2>&1 || ip link add dev vcan0 type vcan",
        "ip link set up vcan0",
    ]


def test_adapter_commands_set_the_bitrate_before_bringing_it_up() -> None:
    assert can_setup_commands("can1", 500_000, restart_ms=0) == [
        "ip link set can1 down",
        "ip link set can1 type can bitrate 500000 restart-ms 0",
        "ip link set up can1",
    ]


@pytest.mark.parametrize("name", ["", "vcan0;reboot", "a b", "x" * 16, "vcan$(id)"])
def test_unsafe_interface_names_are_refused(name: str) -> None:
    with pytest.raises(DriverConfigError, match="CAN interface name"):
        vcan_setup_commands(name)


@pytest.mark.parametrize("bitrate", [0, 2_000_000, 1e6, True])
def test_bad_bitrates_are_refused(bitrate: object) -> None:
    with pytest.raises(DriverConfigError, match="bitrate"):
        can_setup_commands("can0", bitrate)  # type: ignore[arg-type]


def test_setup_script_is_valid_sh_and_picks_vcan_or_adapter() -> None:
    vcan = setup_script("vcan3")
    assert vcan.startswith("#!/bin/sh\n") and "set -e\n" in vcan
    assert "ip link add dev vcan3 type vcan" in vcan
    adapter = setup_script("can0", bitrate=250_000)
    assert "bitrate 250000" in adapter and "type vcan" not in adapter
    if shutil.which("sh"):
        for text in (vcan, adapter):
            assert subprocess.run(["sh", "-n"], input=text, text=True, check=False).returncode == 0


def test_persistent_files_name_the_interface() -> None:
    files = persistent_vcan_files("vcan1")
    assert files["/etc/modules-load.d/vcan.conf"] == "vcan\n"
    assert "Name=vcan1\nKind=vcan" in files["/etc/systemd/network/80-vcan1.netdev"]
    assert "Name=vcan1" in files["/etc/systemd/network/80-vcan1.network"]


@pytest.mark.skipif(shutil.which("sh") is None, reason="no sh")
@pytest.mark.parametrize(
    ("args", "expected"),
    [((), vcan_setup_commands("vcan0")), (("vcan2",), vcan_setup_commands("vcan2")),
     (("can0", "1000000"), can_setup_commands("can0", 1_000_000))],
)
def test_standalone_script_prints_the_same_commands(
    args: tuple[str, ...], expected: list[str]
) -> None:
    out = subprocess.run(["sh", str(SCRIPT), "--print", *args], capture_output=True, text=True,
                         check=True, timeout=10)
    assert out.stdout.splitlines() == expected


@pytest.mark.skipif(shutil.which("sh") is None, reason="no sh")
def test_standalone_script_refuses_a_bad_name() -> None:
    out = subprocess.run(["sh", str(SCRIPT), "--print", "x;y"], capture_output=True, text=True,
                         check=False, timeout=10)
    assert out.returncode == 2 and "bad interface name" in out.stderr
