"""LSL transport against a real LSL outlet in this process, kept on this machine.

liblsl reads its config once per process, from $LSLAPICFG: the fixture writes an lsl_api.cfg with
machine-local resolution and IPv4 only before pylsl is first used, so no multicast leaves the PC.
Every wait is bounded (resolve timeouts, asyncio.wait_for); the module is marked ``lsl``.
"""

from __future__ import annotations

import asyncio
import math
import os
import uuid
from collections.abc import Iterator
from typing import Any

import pytest

from drivers.cart import BreathStream, CartConfig
from drivers.errors import DriverConfigError, TransportError

pytestmark = [pytest.mark.timeout(15)]  # every wait inside is bounded well below this

LSL_API_CFG = """\
[ports]
IPv6 = disable
[multicast]
ResolveScope = machine
"""


@pytest.fixture(scope="module")
def pylsl(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    cfg = tmp_path_factory.mktemp("lsl") / "lsl_api.cfg"
    cfg.write_text(LSL_API_CFG)
    old = os.environ.get("LSLAPICFG")
    os.environ["LSLAPICFG"] = str(cfg)
    import pylsl as module

    yield module
    if old is None:
        os.environ.pop("LSLAPICFG", None)
    else:
        os.environ["LSLAPICFG"] = old


def _outlet(pylsl: Any, name: str, labels: list[tuple[str, str]]) -> Any:
    info = pylsl.StreamInfo(name, "Breath", len(labels), pylsl.IRREGULAR_RATE, pylsl.cf_double64,
                            f"hilbo-test-{name}")
    channels = info.desc().append_child("channels")
    for label, unit in labels:
        ch = channels.append_child("channel")
        ch.append_child_value("label", label)
        ch.append_child_value("unit", unit)
    return pylsl.StreamOutlet(info)


def _config(name: str, **options: object) -> CartConfig:
    return CartConfig.from_dict({"transport": "lsl",
                                 "options": {"stream_name": name, "resolve_timeout_s": 5.0, **options}})


def test_breaths_from_an_lsl_outlet(pylsl: Any) -> None:
    name = f"hilbo-breaths-{uuid.uuid4().hex[:8]}"
    outlet = _outlet(pylsl, name, [("t", "s"), ("VO2", "L/min"), ("VCO2", "L/min"), ("HR", "bpm")])
    samples = [[10.0, 1.2, 1.0, 100.0], [13.0, math.nan, 1.0, 101.0], [16.0, 1.25, 1.05, 102.0],
               [19.0, 1.3, 1.1, 103.0]]

    async def run() -> tuple[list[Any], dict[str, int]]:
        async with BreathStream.from_config(_config(name)) as stream:
            for s in samples:
                outlet.push_sample(s)
            out = [await asyncio.wait_for(anext(stream), 5.0) for _ in range(3)]
            return out, dict(stream.counters)

    records, counters = asyncio.run(run())
    assert [(r.t_s, r.vo2_ml_min, r.vco2_ml_min, r.hr_bpm) for r in records] == [
        (10.0, 1200.0, 1000.0, 100.0), (16.0, 1250.0, 1050.0, 102.0), (19.0, 1300.0, 1100.0, 103.0)]
    assert counters == {"non_finite": 1}


def test_lsl_time_stamp_when_no_time_channel_and_mapped_labels(pylsl: Any) -> None:
    name = f"hilbo-breaths-{uuid.uuid4().hex[:8]}"
    outlet = _outlet(pylsl, name, [("O2 uptake", "mL/min"), ("CO2 output", "mL/min")])

    async def run() -> Any:
        config = _config(name, channels={"vo2_ml_min": "O2 uptake", "vco2_ml_min": "CO2 output"})
        async with BreathStream.from_config(config) as stream:
            outlet.push_sample([900.0, 800.0], 1234.5)
            return await asyncio.wait_for(anext(stream), 5.0)

    rec = asyncio.run(run())
    assert (rec.t_s, rec.vo2_ml_min, rec.vco2_ml_min) == pytest.approx((1234.5, 900.0, 800.0))


def test_missing_channel_names_the_stream_channels(pylsl: Any) -> None:
    name = f"hilbo-breaths-{uuid.uuid4().hex[:8]}"
    outlet = _outlet(pylsl, name, [("t", "s"), ("VO2", "mL/min")])

    async def run() -> None:
        async with BreathStream.from_config(_config(name)):
            pass

    with pytest.raises(DriverConfigError,
                       match=r"no channel labelled 'vco2_ml_min' or 'vco2'.*\['t', 'VO2'\]"):
        asyncio.run(run())
    assert outlet.have_consumers() is False


def test_no_stream_fails_after_the_resolve_timeout(pylsl: Any) -> None:
    async def run() -> None:
        config = _config("hilbo-nobody-" + uuid.uuid4().hex, resolve_timeout_s=0.3)
        async with BreathStream.from_config(config):
            pass

    with pytest.raises(TransportError, match=r"no LSL stream with name='hilbo-nobody-.*within 0.3 s"):
        asyncio.run(run())


def test_lsl_options_are_validated() -> None:
    with pytest.raises(DriverConfigError, match="stream_name and stream_type are both unset"):
        CartConfig.from_dict({"transport": "lsl", "options": {}})
    with pytest.raises(DriverConfigError, match=(
            r"unknown key cart\.options\.channels\.o2 = 'x'; "
            r"allowed keys in \[cart\.options\.channels\]")):
        CartConfig.from_dict({"transport": "lsl",
                              "options": {"stream_type": "Breath", "channels": {"o2": "x"}}})
    with pytest.raises(DriverConfigError, match="format = 'csv' with transport = 'lsl'"):
        CartConfig.from_dict({"transport": "lsl", "format": "csv", "options": {"stream_type": "B"},
                              "csv": {"time_column": "t", "vo2_column": "a", "vco2_column": "b"}})
