"""The commands of the README and of the reference pages under docs/ run as written.

Every fenced shell block is read line by line (continuations joined, comments, pipes and
redirections cut off): each ``hilbo ...`` command must parse with the real command-line parser,
so a renamed subcommand or option fails here; the cheap ones (``--help``, ``--version``,
``config``, ``cart inspect``, ``vcan-setup``) run for real, in the block's order, in a scratch
directory. Each ``make TARGET`` must name a target of the Makefile, and each Python block runs
unless its info string says ``python fragment`` (a sketch with names the reader supplies).
Relative links between the pages must reach a file and, with ``#anchor``, one of its headings.
The result pages are a record of past runs, not instructions, and are not read here.
"""

from __future__ import annotations

import contextlib
import io
import re
import shlex
from dataclasses import dataclass
from pathlib import Path

import pytest

from bridge.cli.main import build_parser, main

ROOT = Path(__file__).resolve().parents[1]
PAGES = ["README.md", *sorted(f"docs/{p.name}" for p in (ROOT / "docs").glob("*.md")
                              if not p.name.startswith("results"))]
SHELL = {"", "sh", "bash", "shell", "console"}
#: Values for the shell variables the blocks set with commands (``EPOCH=$(date +%s)``).
VARIABLES = {"EPOCH": "1765000000"}
#: Subcommands cheap and harmless enough to run for real (no devices, no session, no network).
RUNNABLE = {"config", "cart", "vcan-setup"}


@dataclass(frozen=True)
class Block:
    page: str
    line: int
    info: str
    body: str


def _blocks(page: str) -> list[Block]:
    text = (ROOT / page).read_text(encoding="utf-8")
    found = []
    for m in re.finditer(r"^```([^\n`]*)\n(.*?)^```", text, flags=re.S | re.M):
        found.append(Block(page, text.count("\n", 0, m.start()) + 1, m.group(1).strip(), m.group(2)))
    return found


def _all_blocks() -> list[Block]:
    return [b for page in PAGES for b in _blocks(page)]


def _commands(body: str) -> list[str]:
    joined = re.sub(r"\\\n\s*", " ", body)
    lines = (line.strip() for line in joined.splitlines())
    return [line for line in lines if line and not line.startswith("#")]


def _words(command: str) -> tuple[list[str], str | None]:
    """The command's words up to the first pipe, separator or redirection, and the file its
    stdout is redirected to (``> FILE``), if any."""
    for name, value in VARIABLES.items():
        command = command.replace(f"${name}", value)
    words = shlex.split(command, comments=True)
    out = None
    for i, w in enumerate(words):
        if w in {"|", "||", "&&", ";", "&"} or re.match(r"^\d*[<>]", w):
            if w == ">" and i + 1 < len(words):
                out = words[i + 1]
            return words[:i], out
    return words, out


def _hilbo_argv(words: list[str]) -> list[str] | None:
    if words and words[0] in ("hilbo", ".venv/bin/hilbo"):
        return words[1:]
    return None


def _hilbo_commands() -> list[tuple[Block, str, list[str]]]:
    found = []
    for block in _all_blocks():
        if block.info not in SHELL:
            continue
        for command in _commands(block.body):
            argv = _hilbo_argv(_words(command)[0])
            if argv is not None:
                found.append((block, command, argv))
    return found


def _id(block: Block, command: str) -> str:
    return f"{block.page}:{block.line}: {command[:60]}"


HILBO = _hilbo_commands()


def test_the_pages_show_the_commands_a_reader_needs() -> None:
    subcommands = {argv[0] for _, _, argv in HILBO if argv}
    assert {"sim", "run", "config", "review", "bench", "tune-stopping", "cart", "vcan-setup",
            "virtual-exosuit", "virtual-cart"} <= subcommands
    readme = [argv for block, _, argv in HILBO if block.page == "README.md"]
    assert ["config", "example"] in readme and ["run", "my_session.toml"] in readme


@pytest.mark.parametrize(("block", "command", "argv"), HILBO, ids=[_id(b, c) for b, c, _ in HILBO])
def test_every_hilbo_command_parses(block: Block, command: str, argv: list[str]) -> None:
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            build_parser().parse_args(argv)
    except SystemExit as exc:
        # --help and --version end the parse with status 0; anything else is a wrong command line.
        assert exc.code == 0, f"{block.page}:{block.line}: {command}\n{err.getvalue()}"


def _runnable(argv: list[str]) -> bool:
    return bool(argv) and (argv[0] in RUNNABLE or "--help" in argv or argv == ["--version"])


def _run(argv: list[str], out: str | None, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    capsys.readouterr()
    try:
        code = main(argv)
    except SystemExit as exc:  # --help, --version
        code = int(exc.code or 0)
    captured = capsys.readouterr()
    if out is not None:
        Path(out).write_text(captured.out, encoding="utf-8")
    return code, captured.out + captured.err


RUN_BLOCKS = sorted({b for b, _, argv in HILBO if _runnable(argv)}, key=lambda b: (b.page, b.line))


@pytest.mark.parametrize("block", RUN_BLOCKS, ids=[f"{b.page}:{b.line}" for b in RUN_BLOCKS])
def test_the_cheap_commands_run_in_the_order_shown(block: Block, tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "tests").symlink_to(ROOT / "tests")  # the test data the pages point at
    monkeypatch.chdir(tmp_path)
    ran = 0
    for command in _commands(block.body):
        words, out = _words(command)
        argv = _hilbo_argv(words)
        if argv is None or not _runnable(argv):
            continue
        code, text = _run(argv, out, capsys)
        assert code == 0, f"{block.page}:{block.line}: {command} exited {code}:\n{text}"
        assert "Traceback" not in text
        ran += 1
    assert ran


def test_the_example_config_checks_as_the_readme_says(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(tmp_path)
    assert _run(["config", "example"], "my_session.toml", capsys)[0] == 0
    code, text = _run(["config", "check", "my_session.toml"], None, capsys)
    assert code == 0 and text.startswith("config OK")
    assert "expected end" in text and "pre-flight" in text  # what the README promises it prints


def _make_targets() -> set[str]:
    makefile = (ROOT / "Makefile").read_text(encoding="utf-8")
    return set(re.findall(r"^([a-z][a-z-]*):", makefile, flags=re.M))


def test_every_make_command_names_a_target_of_the_makefile() -> None:
    targets = _make_targets()
    shown = [(b, c) for b in _all_blocks() if b.info in SHELL for c in _commands(b.body)
             if _words(c)[0][:1] == ["make"]]
    assert shown
    for block, command in shown:
        for word in _words(command)[0][1:]:
            if "=" not in word:
                assert word in targets, f"{block.page}:{block.line}: {command}: no target {word!r}"


PYTHON = [b for b in _all_blocks() if b.info.split()[:1] == ["python"] and "fragment" not in b.info]


@pytest.mark.parametrize("block", PYTHON, ids=[f"{b.page}:{b.line}" for b in PYTHON])
def test_every_python_block_runs(block: Block, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    exec(compile(block.body, f"{block.page}:{block.line}", "exec"), {"__name__": "docs_example"})


def test_python_fragments_at_least_compile() -> None:
    fragments = [b for b in _all_blocks() if b.info.split()[:1] == ["python"] and "fragment" in b.info]
    assert PYTHON and fragments
    for block in fragments:
        compile(block.body, f"{block.page}:{block.line}", "exec")


def _slug(heading: str) -> str:
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    text = re.sub(r"^```.*?^```", "", page.read_text(encoding="utf-8"), flags=re.S | re.M)
    return {_slug(h) for h in re.findall(r"^#+ (.+)$", text, flags=re.M)}


def test_every_link_between_the_pages_reaches_its_file_and_heading() -> None:
    checked = 0
    for page in PAGES:
        path = ROOT / page
        text = re.sub(r"^```.*?^```", "", path.read_text(encoding="utf-8"), flags=re.S | re.M)
        for target in re.findall(r"\]\(([^)\s]+)\)", text):
            if re.match(r"^[a-z]+:", target):
                continue
            file_part, _, anchor = target.partition("#")
            dest = (path.parent / file_part).resolve() if file_part else path
            assert dest.exists(), f"{page}: link to missing {target}"
            if anchor:
                assert anchor in _anchors(dest), f"{page}: no heading #{anchor} in {dest.name}"
            checked += 1
    assert checked


def test_every_reference_page_is_linked_from_the_readme() -> None:
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    for page in PAGES[1:]:
        assert f"]({page})" in readme or f"]({page}#" in readme, f"README does not link {page}"


def test_the_readme_stays_a_guide() -> None:
    assert len((ROOT / "README.md").read_bytes()) <= 15_000
