"""scripts/uml_run.py: the user-mode Linux runner behind the vcan tests."""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path
from types import ModuleType

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "uml_run.py"


def load() -> ModuleType:
    spec = importlib.util.spec_from_file_location("uml_run_under_test", SCRIPT)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


uml_run = load()


def test_init_script_loads_can_modules_sets_the_guard_and_quotes_the_command(
    tmp_path: Path,
) -> None:
    text = uml_run._init_script(tmp_path, Path("/work/x y"), {"A": "1 2"}, ["echo", "a'b", "$HOME"])
    assert text.startswith("#!/bin/bash\n")
    for module in ("can.ko", "can-raw.ko", "can-dev.ko", "vcan.ko"):
        assert module in text
    assert "ip link add dev vcan0 type vcan" in text
    assert f"{uml_run.IN_UML_ENV}=1" in text
    assert "export A='1 2'" in text
    assert "cd '/work/x y'" in text
    assert "echo 'a'\"'\"'b' '$HOME'" in text  # shell-quoted: no expansion inside the guest
    # the status is written last, atomically, and the guest powers itself off
    assert text.index("status.tmp") < text.index("/status\n") < text.index("sysrq-trigger")


def test_qemu_init_script_loads_the_can_modules_with_modprobe(tmp_path: Path) -> None:
    text = uml_run._init_script(tmp_path, Path("/w"), {}, ["true"], backend="qemu")
    assert "modprobe \"$m\"" in text and "for m in can can-raw can-bcm can-dev vcan" in text
    assert "/usr/lib/uml/modules" not in text
    assert "ip link add dev vcan0 type vcan" in text


def test_initramfs_archive_is_newc_cpio_with_aligned_entries() -> None:
    data = uml_run._cpio([("init", 0o100755, b"#!/bin/sh\n"), ("lib", 0o040755, b"")])
    names, pos = [], 0
    while True:
        header = data[pos:pos + 110]
        assert header[:6] == b"070701"
        fields = [int(header[6 + 8 * k: 14 + 8 * k], 16) for k in range(13)]
        size, namesize = fields[6], fields[11]
        name = data[pos + 110: pos + 110 + namesize - 1].decode()
        names.append(name)
        pos += 110 + namesize
        pos += -pos % 4
        assert data[pos:pos + size] == (b"#!/bin/sh\n" if name == "init" else b"")
        pos += size + (-size % 4)
        if name == "TRAILER!!!":
            break
    assert names == ["init", "lib", "TRAILER!!!"]
    assert pos == len(data) and len(data) % 4 == 0


def test_guest_follows_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HILBO_GUEST", "qemu")
    assert uml_run.choose_backend() == "qemu"
    monkeypatch.setenv("HILBO_GUEST", "uml")
    assert uml_run.choose_backend() == "uml"


def usable() -> str | None:
    if os.environ.get(uml_run.IN_UML_ENV) == "1":
        return "inside user-mode Linux"
    return uml_run.guest_problem()


@pytest.mark.slow
@pytest.mark.skipif(usable() is not None, reason=f"needs user-mode Linux: {usable()}")
def test_guest_runs_the_command_with_vcan0_and_returns_its_status() -> None:
    result = uml_run.run_in_uml(
        ["/bin/sh", "-c", "cat /sys/class/net/vcan0/type; echo guard=$HILBO_IN_UML; exit 3"],
        timeout_s=60,
    )
    assert result.status == 3, result.console[-2000:]
    assert result.output.split() == ["280", "guard=1"]  # 280 = ARPHRD_CAN
    assert not result.timed_out
    assert not result.work_dir.exists()


@pytest.mark.slow
@pytest.mark.skipif(usable() is not None, reason=f"needs user-mode Linux: {usable()}")
def test_a_hung_guest_is_killed_at_the_timeout() -> None:
    result = uml_run.run_in_uml(["/bin/sleep", "120"], timeout_s=6)
    assert result.timed_out and result.status is None
    assert result.elapsed_s < 20
