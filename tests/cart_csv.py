"""A COSMED-like breath CSV for tests that replay a cart export (clock times, VO2/VCO2 in ml/min).

Used by tests/drivers/test_cart_reject_stop.py and tests/bridge/test_console_lost.py.
"""

from __future__ import annotations

from pathlib import Path


def write_cosmed_like_csv(path: Path, n: int) -> Path:
    """``n`` breaths 3 s apart, about 1000 ml/min VO2, in the layout of a COSMED export.

    Returns:
        ``path``.
    """
    rows = ["t,VO2,VCO2,R", "s,mL/min,mL/min,---"]
    for i in range(n):
        t = 3 * i + 3
        rows.append(f"0:{t // 60:02d}:{t % 60:02d},{1000 + i % 7},{850 + i % 5},0.85")
    path.write_text("\n".join(rows) + "\n")
    return path


def replay_config_toml(tmp_path: Path, cart_path: Path, csv_extra: str = "") -> Path:
    """The example config replaying ``cart_path`` (from :func:`write_cosmed_like_csv`) at full
    speed on python-can's virtual bus, its sessions under ``tmp_path / "out"``.

    Args:
        tmp_path: Where the config and the sessions go.
        cart_path: The CSV to replay.
        csv_extra: Further ``[cart.csv]`` lines.

    Returns:
        The config's path, ``tmp_path / "s.toml"``.
    """
    root = Path(__file__).resolve().parents[1]
    text = (root / "bridge" / "config_example.toml").read_text()
    start, end = text.index("[cart]"), text.index("[can]")
    cart = (f'[cart]\ntransport = "replay"\nformat = "csv"\n[cart.options]\npath = "{cart_path}"\n'
            'speed = "max"\n[cart.csv]\ntime_column = "t"\nvo2_column = "VO2"\nvco2_column = "VCO2"\n'
            f'time_format = "hh:mm:ss"\nskip_rows = 1\n{csv_extra}\n')
    text = text[:start] + cart + text[end:]
    text = text.replace('interface = "socketcan"', 'interface = "virtual"')
    text = text.replace('out_dir = "sessions"', f'out_dir = "{tmp_path / "out"}"')
    path = tmp_path / "s.toml"
    path.write_text(text)
    return path
