"""The virtual-device CLIs: 2 for options refused before serving, 1 for a failure at run time."""

from __future__ import annotations

import socket
import sys

import pytest

from virtual_hw import cli_cart, cli_exosuit


def test_cart_port_in_use_exits_1_naming_the_address(capsys: pytest.CaptureFixture[str]) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        code = cli_cart.main(["--port", str(port), "--minutes", "0.01"])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err
    assert "hilbo virtual-cart: error:" in err and str(port) in err and "address already in use" in err


def test_cart_bad_body_mass_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_cart.main(["--body-mass-kg", "5", "--minutes", "0.01", "--speed", "max"]) == 2
    assert "--body-mass-kg 5: body_mass_kg=5.0 must be a number in [20, 250] kg" in capsys.readouterr().err


@pytest.mark.parametrize("seed", ["-1", "two"])
def test_cart_bad_seed_is_a_usage_error_naming_the_seed(
        seed: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        cli_cart.main(["--seed", seed, "--minutes", "0.01", "--speed", "max"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    (line,) = [line for line in err.splitlines() if "error:" in line]
    assert line.endswith(f"argument --seed: seed must be a non-negative integer, got {seed!r}")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="socketcan is Linux-only")
def test_exosuit_on_a_bus_that_cannot_be_opened_exits_1(capsys: pytest.CaptureFixture[str]) -> None:
    code = cli_exosuit.main(["--interface", "socketcan", "--channel", "hilbo-nosuch0", "--lifetime", "1"])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err
    assert "hilbo virtual-exosuit: error: cannot open CAN bus socketcan:hilbo-nosuch0" in err


def test_exosuit_speed_max_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_exosuit.main(["--interface", "virtual", "--channel", "x", "--speed", "max"]) == 2
    assert "--speed max" in capsys.readouterr().err
