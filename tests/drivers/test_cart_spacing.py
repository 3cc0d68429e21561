"""A time column in the wrong unit is caught by the breaths' spacing (drivers/cart/pipeline.py):
``time_format = "min"`` on a seconds column makes breaths 180 s apart, which passes every
per-breath check; ``config check`` and the session's stream refuse it with one clear line, and
``config check`` says "config OK" only once the cart file has been read."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

import bridge.cli.main as cli
from drivers.cart import BreathStream, CartConfig
from drivers.cart.errors import CartError
from drivers.cart.pipeline import check_breath_spacing

pytestmark = pytest.mark.timeout(60)


def write_seconds_csv(path: Path, n: int = 100) -> Path:
    rows = ["t,VO2,VCO2"] + [f"{3 * i + 3},{1000 + i % 7},{850 + i % 5}" for i in range(n)]
    path.write_text("\n".join(rows) + "\n")
    return path


def cart(path: Path, time_format: str) -> dict[str, object]:
    return {"transport": "replay", "format": "csv", "options": {"path": str(path), "speed": "max"},
            "csv": {"time_column": "t", "vo2_column": "VO2", "vco2_column": "VCO2",
                    "time_format": time_format}}


def config_toml(tmp_path: Path, cart_path: Path, time_format: str) -> Path:
    text = (Path(cli.__file__).parents[1] / "config_example.toml").read_text()
    start, end = text.index("[cart]"), text.index("[can]")
    section = (f'[cart]\ntransport = "replay"\nformat = "csv"\n[cart.options]\npath = "{cart_path}"\n'
               'speed = "max"\n[cart.csv]\ntime_column = "t"\nvo2_column = "VO2"\nvco2_column = "VCO2"\n'
               f'time_format = "{time_format}"\n')
    text = (text[:start] + section + text[end:]).replace('interface = "socketcan"', 'interface = "virtual"')
    text = text.replace('out_dir = "sessions"', f'out_dir = "{tmp_path / "out"}"')
    path = tmp_path / "s.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize(("times", "ok"), [
    ([3.0 * i for i in range(8)], True), ([10.0 * i for i in range(8)], True),
    ([180.0 * i for i in range(8)], False), ([0.05 * i for i in range(8)], False),
    ([0.0], True),
])
def test_the_median_spacing_must_be_one_a_person_breathes_at(times: list[float], ok: bool) -> None:
    if ok:
        check_breath_spacing(times)
    else:
        with pytest.raises(CartError, match=r"median .* s apart.*time_format"):
            check_breath_spacing(times)


def test_a_stream_in_the_wrong_time_unit_stops_with_the_reason(tmp_path: Path) -> None:
    path = write_seconds_csv(tmp_path / "a.csv")

    async def drain(time_format: str) -> int:
        n = 0
        async with BreathStream.from_config(CartConfig.from_dict(cart(path, time_format))) as stream:
            async for _ in stream:
                n += 1
        return n

    assert asyncio.run(drain("s")) == 100
    with pytest.raises(CartError, match=r"median 180 s apart.*seconds read as minutes"):
        asyncio.run(drain("min"))


def test_config_check_refuses_it_and_never_says_ok_first(tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    path = write_seconds_csv(tmp_path / "a.csv")
    assert cli.main(["config", "check", str(config_toml(tmp_path, path, "s")), "--samples", "0"]) == 0
    assert capsys.readouterr().out.startswith("config OK")
    assert cli.main(["config", "check", str(config_toml(tmp_path, path, "min")), "--samples", "0"]) == 1
    cap = capsys.readouterr()
    assert "config OK" not in cap.out
    assert "median 180 s apart" in cap.err and len(cap.err.strip().splitlines()) == 1
    # A cart file that does not fit (a column missing) is not "config OK" either.
    path.write_text(path.read_text().replace("VCO2", "CO2", 1))
    assert cli.main(["config", "check", str(config_toml(tmp_path, path, "s")), "--samples", "0"]) == 1
    assert "config OK" not in capsys.readouterr().out
