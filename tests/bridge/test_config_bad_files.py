"""Config files and the files a config names: bounded, regular, nested no deeper than a config
needs; ``~`` in ``out_dir``; a warning for a live view other machines can reach."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from file_inputs import NOT_REGULAR, not_regular_file
from hypothesis import given, settings
from hypothesis import strategies as st

import bridge.run
from bridge.cli.main import main
from bridge.config import config_warnings, example_config_text, parse_config
from bridge.errors import BridgeConfigError, BridgeError

pytestmark = pytest.mark.timeout(60)


def with_keys(table: str, lines: str) -> str:
    """The example config with ``lines`` added at the top of ``[table]``."""
    text = example_config_text()
    head = f"\n[{table}]\n"
    assert head in text
    return text.replace(head, f"{head}{lines}\n", 1)


def check(tmp_path: Path, text: str, capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    path = tmp_path / "c.toml"
    path.write_text(text)
    code = main(["config", "check", str(path), "--samples", "0"])
    out, err = capsys.readouterr()
    return code, out, err


def one_line_error(err: str, *needles: str) -> None:
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("hilbo config check: invalid config: "), lines[0]
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


def test_an_array_nested_100000_deep_is_an_error_not_a_recursion_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = with_keys("session", "nested = " + "[" * 100_000 + "]" * 100_000)
    code, out, err = check(tmp_path, text, capsys)
    assert code == 1 and out == ""
    one_line_error(err, "c.toml", "nested deeper")


def test_nesting_deeper_than_a_config_needs_is_refused() -> None:
    with pytest.raises(BridgeConfigError, match="nested more than 16 levels"):
        parse_config(with_keys("session", "nested = " + "[" * 40 + "]" * 40), source="deep.toml")


def test_out_dir_with_a_tilde_is_the_home_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    text = example_config_text().replace('out_dir = "sessions"', 'out_dir = "~/hilbo-sessions"')
    cfg = parse_config(text)
    assert cfg.session.out_dir == tmp_path / "home" / "hilbo-sessions"
    code, out, _ = check(tmp_path, text, capsys)
    assert code == 0 and f"output in {tmp_path / 'home' / 'hilbo-sessions'}" in out
    assert not (Path.cwd() / "~").exists()


def test_a_relative_out_dir_is_shown_with_where_it_resolves(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    code, out, _ = check(tmp_path, example_config_text(), capsys)
    assert code == 0 and f"output in sessions ({tmp_path / 'sessions'})" in out


def test_a_tilde_of_an_unknown_user_is_refused() -> None:
    text = example_config_text().replace('out_dir = "sessions"', 'out_dir = "~no-such-user-hilbo/s"')
    with pytest.raises(BridgeConfigError, match=r"session.out_dir = '~no-such-user-hilbo/s'.*unknown"):
        parse_config(text)


@pytest.mark.parametrize(("host", "warned"), [("0.0.0.0", True), ("192.168.1.20", True), ("lab-pc", True),
                                              ("127.0.0.1", False), ("localhost", False), ("::1", False)])
def test_a_live_host_other_than_loopback_is_warned_about(host: str, warned: bool) -> None:
    cfg = parse_config(with_keys("live", f'host = "{host}"'))
    found = [w for w in config_warnings(cfg) if w.startswith("live.host")]
    assert bool(found) == warned
    if warned:
        assert repr(host) in found[0] and "no authentication" in found[0]


def test_config_check_and_run_warn_about_a_reachable_live_host(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    text = with_keys("live", 'host = "0.0.0.0"')
    code, _, err = check(tmp_path, text, capsys)
    assert code == 0 and "hilbo config check: warning: live.host = '0.0.0.0'" in err

    async def no_session(*args: object, **kwargs: object) -> None:
        raise BridgeError("stopped before the session (test)")

    monkeypatch.setattr(bridge.run, "run_session", no_session)
    monkeypatch.chdir(tmp_path)
    assert main(["run", str(tmp_path / "c.toml"), "--no-view"]) == 1
    err = capsys.readouterr().err
    assert "hilbo run: warning: live.host = '0.0.0.0'" in err


@pytest.fixture(params=NOT_REGULAR)
def not_a_file(request: pytest.FixtureRequest, tmp_path: Path) -> tuple[Path, str]:
    return not_regular_file(request.param, tmp_path, "population.csv")


def test_a_prior_table_that_is_not_a_regular_file(tmp_path: Path, not_a_file: tuple[Path, str],
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    path, kind = not_a_file
    code, _, err = check(tmp_path, with_keys("prior", f'table = "{path}"'), capsys)
    assert code == 1
    one_line_error(err, f"prior.table = '{path}'", kind)


def test_a_config_that_is_not_a_regular_file(tmp_path: Path, not_a_file: tuple[Path, str],
                                             capsys: pytest.CaptureFixture[str]) -> None:
    path, kind = not_a_file
    assert main(["config", "check", str(path)]) == 1
    one_line_error(capsys.readouterr().err, str(path), kind)


_EXAMPLE_LINES = example_config_text().splitlines()


@settings(max_examples=100, deadline=None)
@given(line=st.integers(0, len(_EXAMPLE_LINES) - 1),
       value=st.text(alphabet=st.characters(blacklist_categories=("Cs",)), max_size=40))
def test_a_damaged_line_is_a_config_error_or_a_config(line: int, value: str) -> None:
    lines = list(_EXAMPLE_LINES)
    key, sep, _ = lines[line].partition("=")
    lines[line] = f"{key}{sep} {value}" if sep else value
    try:
        cfg = parse_config("\n".join(lines), source="fuzz.toml")
    except BridgeConfigError as err:
        assert str(err)
    else:
        assert cfg.source == "fuzz.toml"


@pytest.mark.parametrize(("keys", "start"), [
    ("accept_stop = false\naccept_z = 2.5", "protocol.accept_z = 2.5 has no effect"),
    ('file_mode = "0644"', "session.file_mode = '0644' lets other users"),
])
def test_settings_that_do_nothing_or_expose_health_data_are_warned_about(keys: str, start: str) -> None:
    assert not config_warnings(parse_config(example_config_text()))
    text = example_config_text()
    for line in keys.splitlines():  # the example's own line of that key, replaced
        key = line.split("=")[0].strip()
        text = re.sub(rf"(?m)^#? ?{key} = .*$", line, text, count=1)
        assert line in text
    found = [w for w in config_warnings(parse_config(text)) if w.startswith(start)]
    assert len(found) == 1


def test_a_cart_host_with_a_port_is_refused_naming_both() -> None:
    text = example_config_text().replace('host = "127.0.0.1" ', 'host = "127.0.0.1:5050" ', 1)
    with pytest.raises(BridgeConfigError, match=r"cart.options.host = '127.0.0.1:5050': expected a host "
                                                r"name or address without a port \(the port is its own "
                                                r"key, port = 5050 here\)"):
        parse_config(text)


def test_a_file_mode_given_as_a_number_says_what_the_text_looks_like() -> None:
    text = example_config_text().replace('file_mode = "0600"', "file_mode = 600", 1)
    assert "file_mode = 600" in text
    with pytest.raises(BridgeConfigError, match=r'session.file_mode = 600: expected octal permission bits '
                                                r'such as "0600"'):
        parse_config(text)
