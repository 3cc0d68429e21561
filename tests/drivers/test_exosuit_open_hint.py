"""A SocketCAN interface that is missing or down: the error says how to bring one up."""

from __future__ import annotations

import errno
import os

import can
import pytest

from drivers.errors import TransportError
from drivers.exosuit.endpoint import CanBusConfig, CanEndpoint


@pytest.mark.parametrize("code", [errno.EAFNOSUPPORT, errno.ENODEV, errno.ENETDOWN])
async def test_a_missing_socketcan_interface_says_how_to_bring_one_up(code: int) -> None:
    def no_interface(**kwargs: object) -> can.BusABC:
        raise OSError(code, os.strerror(code))

    endpoint = CanEndpoint(CanBusConfig("socketcan", "vcan0"), bus_factory=no_interface)
    with pytest.raises(TransportError, match=r"cannot open CAN bus socketcan:vcan0: .*is vcan0 up\? "
                                             r".*hilbo vcan-setup"):
        await endpoint.open()


async def test_other_open_failures_get_no_socketcan_hint() -> None:
    def refused(**kwargs: object) -> can.BusABC:
        raise OSError(errno.EACCES, "Permission denied")

    for config in (CanBusConfig("socketcan", "can0"), CanBusConfig("virtual", "x")):
        with pytest.raises(TransportError) as info:
            await CanEndpoint(config, bus_factory=refused).open()
        assert "vcan-setup" not in str(info.value)
